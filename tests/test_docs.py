"""The user's guide, docs/ and benchmarks/README.md as documentation: every relative link lands on a file (and a
heading, where it names one); every file of the repository and every module of nerfexp a guide (README.md,
docs/*.md outside docs/results) names exists; and a guide says what is true now, never when it became so.

What a guide may not name, and how each is told from legitimate text:

- an issue or pull request by number: "issue 51", "issues 7", "PR 12", "#51" (not an anchor "(#the-step)", an HTML
  entity "&#39;" or a heading's "# "); another project's issue is cited by a link to it, whose address is not read;
- a date: 2026-11-29, except as a folder of a path (Hydra's ``outputs/2026-11-22/10-00-00``), and "Nov 28",
  "28 November" or "March 2020" (a capitalised month and a day or a year; a year alone is a citation's);
- a commit: a run of 7 to 40 lowercase hexadecimal digits with a letter and a digit among them, standing alone (not
  part of a file name such as ``alexnet-owt-7be5be79.pth``, a path or a longer word), or "commit" followed by hex
  digits. A SHA-256 digest is not a commit: it is 64 digits, written in full somewhere in the guides, and a run
  that begins a digest written in full there (``7be5be79``, ``df73285e...``) is that digest's prefix;
- history in words, in prose (inline code and fenced blocks are program output and commands, left out): "not kept",
  "that day", "the old default(s)", "a week ago", "yesterday".

Measurements and their history live in docs/results/ (which names commits and dates: what was measured when) and
in git.

What a guide names must exist: a path from the repository's root that starts at one of its folders (src/nerfexp,
tests, benchmarks, conf, sweeps, docs, .ci; words in capitals are placeholders, {a,b} names both), and a
``nerfexp.a.b.C.d`` that is a module of src/nerfexp or a name one defines, read from the source without importing it
(the names of the flat layout that saved runs hold, which nerfexp reads as today's, are named on purpose).
"""

import ast
import itertools
import re
from pathlib import Path

import pytest

from tests.helpers import REPO

PAGES = sorted([REPO / "README.md", REPO / "benchmarks" / "README.md", *(REPO / "docs").rglob("*.md")])
# the README and the guides; docs/results/ holds measurements, which name their commits and dates
GUIDES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
LINK = re.compile(r"\]\(([^)\s]+)\)")

ISSUE = re.compile(r"\b(?:[Ii]ssues?|PRs?|[Pp]ull requests?) #?\d+\b|(?<![\w&#/])#\d+\b")
MONTH = (
    r"(?:January|February|March|April|May|June|July|August|September|October|November|December"
    r"|Jan|Feb|Mar|Apr|Jun|Jul|Aug|Sept?|Oct|Nov|Dec)"
)
DATE = re.compile(
    rf"(?<![\w/-])\d{{4}}-\d{{2}}-\d{{2}}(?![\w-])|\b{MONTH}\.? (?:\d{{1,2}}|\d{{4}})\b|\b\d{{1,2}} {MONTH}\b"
)
# a commit as git abbreviates it: 7 to 40 hexadecimal digits, with a letter and a digit among them, standing alone
COMMIT = re.compile(r"(?<![\w./#-])(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}(?![\w/-]|\.\w)")
COMMIT_WORD = re.compile(r"\bcommits? `?[0-9a-f]{4,40}\b")
DIGEST = re.compile(r"(?<![\w])[0-9a-f]{64}(?!\w)")
HISTORY = re.compile(r"\b(?:not kept|that day|the old defaults?|a week ago|yesterday)\b", re.IGNORECASE)
CODE = re.compile(r"```.*?```|`(?:[^`\n]|\n(?!\n))*`", re.DOTALL)  # fenced blocks, inline code (within a paragraph)

# Sections another part of the work rewrites as a whole (the occupancy grid's, with its new sampler): left to it.
# Each must still exist and still need leaving out, so that the entry goes once the section is rewritten.
REWRITTEN_ELSEWHERE = {"docs/acceleration.md": {"The grid's quality loss"}}

# A path of the repository as a guide writes it (from the repository's root); words in capitals are placeholders
# (conf/data/FORMAT.yaml), {a,b} names both, * any.
REPO_PATH = re.compile(r"(?<![\w./-])((?:src/nerfexp|tests|benchmarks|conf|sweeps|docs|\.ci)/[\w./{},*-]*)")
PLACEHOLDER = re.compile(r"[A-Z]{3,}")
# nerfexp's modules and their names as a guide writes them (nerfexp.nerf.hashgrid.HashGridEncoding)
MODULE_NAME = re.compile(r"(?<![\w.])nerfexp(?:\.[A-Za-z_]\w*)+")
RUN_FILES = {"nerfexp.log"}  # a run's files whose names read as a module's


def heading_anchor(title: str) -> str:
    """A Markdown heading's anchor as GitHub makes it: lower case, punctuation but - and _ dropped, spaces -."""
    return re.sub(r"[^\w\- ]", "", title.strip().lower()).replace(" ", "-")


def headings(text: str) -> list[tuple[int, int, str]]:
    """``text``'s headings outside fenced code: (line index, level, title)."""
    found, fenced = [], False
    for index, line in enumerate(text.splitlines()):
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and (heading := re.match(r"(#+)\s+(.*)", line)):
            found.append((index, len(heading[1]), heading[2].strip()))
    return found


def anchors(page: Path) -> set[str]:
    """The anchors of ``page``'s headings, those inside fenced code left out."""
    return {heading_anchor(title) for _, _, title in headings(page.read_text())}


def split_sections(text: str, titles: set[str]) -> tuple[str, dict[str, str]]:
    """``text`` without the sections headed by ``titles`` (each to the next heading of its level or above), and
    those sections by title."""
    lines, sections, marks = text.splitlines(), {}, headings(text)
    cut = set()
    for number, (start, level, title) in enumerate(marks):
        if title in titles:
            end = next((i for i, lv, _ in marks[number + 1 :] if lv <= level), len(lines))
            sections[title] = "\n".join(lines[start:end])
            cut.update(range(start, end))
    return "\n".join(line for i, line in enumerate(lines) if i not in cut), sections


def digests() -> set[str]:
    """The SHA-256 digests written in full anywhere in the guides."""
    return {d for page in GUIDES for d in DIGEST.findall(page.read_text())}


def history(text: str, known_digests: set[str]) -> list[str]:
    """What in ``text`` dates it: issue numbers, dates, commits, history in words (see the module's docstring)."""
    commits = [c for c in COMMIT.findall(text) if not any(d.startswith(c) for d in known_digests)]
    return [
        *ISSUE.findall(text),
        *DATE.findall(text),
        *commits,
        *COMMIT_WORD.findall(text),
        *HISTORY.findall(CODE.sub("", text)),
    ]


def named_paths(text: str) -> list[str]:
    """The repository's paths ``text`` names outside its links' targets, braces expanded, placeholders left out."""
    found = []
    for path in REPO_PATH.findall(LINK.sub("]", text)):
        path = path.rstrip(".,:;")
        parts = re.split(r"\{([^}]*)\}", path)  # the text between braces at the odd indices
        choices = [part.split(",") if i % 2 else [part] for i, part in enumerate(parts)]
        found += ["".join(choice) for choice in itertools.product(*choices)]
    return [path for path in found if not PLACEHOLDER.search(path)]


def module_names(module: Path) -> dict[str, set[str]]:
    """The names ``module`` defines at its top level (functions, classes, assignments, imports), each with its
    members where it is a class."""
    names = {}
    for node in ast.parse(module.read_text()).body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            names[node.name] = set()
        elif isinstance(node, ast.ClassDef):
            members = set()
            for item in node.body:
                if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                    members.add(item.name)
                elif isinstance(item, (ast.Assign, ast.AnnAssign)):
                    targets = item.targets if isinstance(item, ast.Assign) else [item.target]
                    members.update(t.id for t in targets if isinstance(t, ast.Name))
            names[node.name] = members
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            for target in targets:
                names.update({n.id: set() for n in ast.walk(target) if isinstance(n, ast.Name)})
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names.update({(alias.asname or alias.name).split(".")[0]: set() for alias in node.names})
    return names


def missing_module_name(name: str) -> str | None:
    """Why ``name`` (``nerfexp.a.b.C.d``) is not a module of src/nerfexp or a name one defines; None where it is."""
    parts = name.split(".")
    for end in range(len(parts), 0, -1):
        base = REPO / "src" / Path(*parts[:end])
        module = base.with_suffix(".py") if base.with_suffix(".py").is_file() else base / "__init__.py"
        if module.is_file():
            rest = parts[end:]
            break
    else:
        return f"{name}: no such module"
    defined = module_names(module)
    if rest and rest[0] not in defined and not (module.name == "__init__.py" and (module.parent / rest[0]).exists()):
        return f"{name}: {module.relative_to(REPO)} defines no {rest[0]}"
    if len(rest) > 1 and defined.get(rest[0]) and rest[1] not in defined[rest[0]]:
        return f"{name}: {rest[0]} in {module.relative_to(REPO)} has no {rest[1]}"
    return None


def old_names() -> tuple[str, ...]:
    """The names of an earlier layout that saved runs hold and nerfexp reads as today's (``MOVED_TARGETS``): a guide
    names them to say so."""
    source = (REPO / "src/nerfexp/rundir/trained.py").read_text()
    table = next(
        node.value
        for node in ast.parse(source).body
        if isinstance(node, ast.Assign) and any(getattr(t, "id", "") == "MOVED_TARGETS" for t in node.targets)
    )
    return tuple(ast.literal_eval(table))


def test_heading_anchor_follows_github():
    assert heading_anchor("Sparse gradients and LazyAdam (opt-in)") == "sparse-gradients-and-lazyadam-opt-in"
    assert heading_anchor("Sparse tables (`sweeps/sparse_tables.yaml`)") == "sparse-tables-sweepssparse_tablesyaml"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(REPO)))
def test_every_relative_link_lands(page):
    broken = []
    for target in LINK.findall(page.read_text()):
        if re.match(r"[a-z]+:", target) or target.startswith("<"):  # a URL, mailto:, an autolink
            continue
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists():
            broken.append(f"{target}: no such file")
        elif anchor and file.suffix == ".md" and anchor not in anchors(file):
            broken.append(f"{target}: no such heading")
    assert not broken, broken


@pytest.mark.parametrize(
    "text, found",
    [
        ("asked for by issue 51 and Issue 7", ["issue 51", "Issue 7"]),
        ("nerfstudio's issue #1104, see #51", ["issue #1104", "#51"]),
        ("[the step](#the-step), &#39;, ## Heading 2", []),
        ("on 2026-11-29, Nov 28, 3 December, in March 2020", ["2026-11-29", "Nov 28", "3 December", "March 2020"]),
        ("Mildenhall et al. (ECCV 2020), `tags=['2024']`, 2048 rays", []),
        ("nerfexp-render outputs/2026-11-22/10-00-00-123456, in May", []),
        ("at commit 4e367d5, 2654435761 and 0.9743", ["4e367d5", "commit 4e367d5"]),
        ("taken out by commit 1234 again", ["commit 1234"]),
        ("alexnet-owt-7be5be79.pth, `7be5be79`, df73285e..., deadbeef, #e0e0e0ff", []),
        ("a kernel measured and not kept, that day; the old defaults", ["not kept", "that day", "the old defaults"]),
        ("says `measured now, not kept: FILE cannot be written`", []),
    ],
)
def test_history_finds_what_dates_a_text_and_nothing_else(text, found):
    known = {  # AlexNet's weights and LPIPS 0.1's heads, as docs/metrics.md and docs/errors.md give them
        "7be5be791159472b1fbf3c69796f7cb30dca7ad8466c2df70058c37116cdee02",
        "df73285e35b22355a2df87cdb6b70b343713b667eddbda73e1977e0c860835c0",
    }
    assert history(text, known) == found


@pytest.mark.parametrize("page", GUIDES, ids=lambda p: str(p.relative_to(REPO)))
def test_a_guide_names_no_issue_date_commit_or_history(page):
    name = str(page.relative_to(REPO))
    text, pending = split_sections(page.read_text(), REWRITTEN_ELSEWHERE.get(name, set()))
    known = digests()
    found = history(text, known)
    assert not found, f"{name} dates itself ({found}): what was measured goes to docs/results/, history to git"
    for title in REWRITTEN_ELSEWHERE.get(name, set()):
        assert title in pending and history(pending[title], known), (
            f"{name}: '{title}' no longer needs leaving out of this test: remove it from REWRITTEN_ELSEWHERE"
        )


def test_named_paths_expand_braces_and_leave_placeholders_out():
    text = "`benchmarks/results/speed.{json,md}`, conf/data/FORMAT.yaml, [x](../tests/helpers.py), src/nerfexp/nerf/."
    assert named_paths(text) == ["benchmarks/results/speed.json", "benchmarks/results/speed.md", "src/nerfexp/nerf/"]


@pytest.mark.parametrize("page", GUIDES, ids=lambda p: str(p.relative_to(REPO)))
def test_every_path_a_guide_names_exists(page):
    missing = [path for path in named_paths(page.read_text()) if not any(REPO.glob(path.rstrip("/")))]
    assert not missing, f"{page.relative_to(REPO)} names files that do not exist: {missing}"


def test_module_names_are_checked_against_the_source():
    assert missing_module_name("nerfexp.nerf.hashgrid.HashGridEncoding.parameter_groups") is None
    assert missing_module_name("nerfexp.rundir.trained.MOVED_TARGETS") is None
    assert missing_module_name("nerfexp.nerf") is None
    assert missing_module_name("nerfexp.nerf.hashgrid.NoSuchEncoding") is not None
    assert missing_module_name("nerfexp.nerf.hashgrid.HashGridEncoding.no_such_method") is not None
    assert missing_module_name("nerfexp.no_such_module.f") is not None


@pytest.mark.parametrize("page", GUIDES, ids=lambda p: str(p.relative_to(REPO)))
def test_every_module_a_guide_names_exists(page):
    old = [name.rstrip(".") for name in old_names()]
    names = {n for n in MODULE_NAME.findall(page.read_text()) if not any(n == o or n.startswith(o + ".") for o in old)}
    missing = [why for name in sorted(names - RUN_FILES) if (why := missing_module_name(name))]
    assert not missing, f"{page.relative_to(REPO)} names what nerfexp does not hold: {missing}"
