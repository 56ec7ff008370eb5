"""benchmarks/: each script one line of benchmarks/README.md, every script a file names there to be run, and each
script's imports found from where it lies (a script moved without its neighbours, or a neighbour retired, fails
here rather than when someone runs it). A script that runs in another tool's environment says so in its docstring
("Runs in nerfstudio's own environment"): its imports are that environment's, so it is not loaded here, and it
imports nothing of nerfexp, which that environment does not hold."""

import ast
import re
import runpy
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import REPO

BENCHMARKS = REPO / "benchmarks"
RECORDS = BENCHMARKS / "results"  # what the scripts wrote, each with the command as it ran then
SCRIPTS = sorted(path for path in BENCHMARKS.rglob("*")
                 if path.suffix in (".py", ".sh") and RECORDS not in path.parents)
# a script as a file names it: its path (lower case: FOLDER/NAME.py is a placeholder), or the module python -m runs
NAMED = re.compile(r"benchmarks/[a-z0-9_/]+\.(?:py|sh)\b|(?<=-m )benchmarks(?:\.\w+)+")
TEXT = (".md", ".py", ".sh", ".yaml", ".toml", ".cfg", ".txt", ".gitignore")  # not .json: records of runs
# how a script's docstring says that it runs in another tool's environment, not nerfexp's; the tool's name captured
ELSEWHERE = re.compile(r"\bRuns in ([\w.-]+)'s own environment\b")


def named_scripts(text: str) -> set[str]:
    """The benchmark scripts ``text`` names, as paths relative to the repository: ``benchmarks.accuracy.quadrature``
    (a module, for ``python -m``) is ``benchmarks/accuracy/quadrature.py``."""
    return {name if "/" in name else name.replace(".", "/") + ".py" for name in NAMED.findall(text)}


def environment(script: Path) -> str | None:
    """The other tool whose environment ``script`` runs in, as its docstring says (``ELSEWHERE``); None where it runs
    in nerfexp's. Read from the source, not imported."""
    doc = " ".join((ast.get_docstring(ast.parse(script.read_text())) or "").split())
    found = ELSEWHERE.search(doc)
    return found[1] if found and found[1] != "nerfexp" else None


def imported_modules(script: Path) -> set[str]:
    """Every module ``script`` imports, at any depth of its code: ``from a.b import c`` imports ``a.b``."""
    found = set()
    for node in ast.walk(ast.parse(script.read_text())):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            found.add(node.module)
    return found


def naming_files() -> list[Path]:
    """The repository's text files (git's, the records under benchmarks/results left out) that name a script."""
    listed = subprocess.run(["git", "ls-files"], cwd=REPO, capture_output=True, text=True, check=True).stdout
    files = [REPO / name for name in listed.splitlines() if name.endswith(TEXT)]
    return [f for f in files if f.is_file() and RECORDS not in f.parents and named_scripts(f.read_text())]


def test_named_scripts_finds_paths_and_modules_only():
    text = ("python benchmarks/kernels/hashgrid.py; `python -m benchmarks.accuracy.quadrature`; bash "
            "benchmarks/gpu/gpu_check.sh; benchmarks/results/hashgrid.md; docs/benchmarks.md; nerfexp.benchmarks; "
            "python benchmarks/FOLDER/NAME.py")
    assert named_scripts(text) == {"benchmarks/kernels/hashgrid.py", "benchmarks/accuracy/quadrature.py",
                                   "benchmarks/gpu/gpu_check.sh"}


@pytest.mark.parametrize("file", naming_files(), ids=lambda f: str(f.relative_to(REPO)))
def test_every_script_a_file_names_is_there(file):
    missing = sorted(name for name in named_scripts(file.read_text()) if not (REPO / name).is_file())
    assert not missing, f"{file.relative_to(REPO)} names scripts that are not there: {missing}"


def test_the_readme_has_one_line_per_script_each_with_its_answer():
    lines = (BENCHMARKS / "README.md").read_text().splitlines()
    named = {}
    for line in lines:
        for script in re.findall(r"\[`([\w/]+\.(?:py|sh))`\]", line):
            named.setdefault(script, []).append(line)
    scripts = {path.relative_to(BENCHMARKS).as_posix() for path in SCRIPTS}
    assert set(named) == scripts, "benchmarks/README.md: scripts without a line, or lines without a script"
    assert all(len(found) == 1 for found in named.values()), "a script with more than one line"
    for script, (line,) in named.items():
        # what it answers, then where: a results page linked, or the record it writes elsewhere
        assert re.search(r"\]\((\.\./docs/)?results/[^)]+\.md(#[\w-]+)?\)|no record", line), script


def test_scripts_live_in_folders_of_what_they_measure():
    loose = [path.name for path in SCRIPTS if path.parent == BENCHMARKS]
    assert not loose, f"scripts directly in benchmarks/, outside a folder of what they measure: {loose}"


@pytest.mark.parametrize(
    "doc, found",
    [
        ("Runs in nerfstudio's own environment (``pip install nerfstudio``), not nerfexp's.", "nerfstudio"),
        ("the peer half.\nRuns in\nnerfstudio's own environment, not nerfexp's", "nerfstudio"),  # across lines
        ("Runs in nerfexp's own environment.", None),
        ("its test views rendered in the peer's environment (``--peer-python``)", None),
        ("", None),
    ],
    ids=["one line", "across lines", "nerfexp's own", "another environment's words", "no docstring"],
)
def test_environment_is_read_from_the_docstring(doc, found, tmp_path):
    script = tmp_path / "script.py"
    script.write_text(f'"""{doc}"""\n\nimport no_such_module_here\n' if doc else "import no_such_module_here\n")
    assert environment(script) == found


def test_imported_modules_finds_every_absolute_import(tmp_path):
    script = tmp_path / "script.py"
    script.write_text("import a.b, c\nfrom nerfexp.x import y\nfrom . import z\n\ndef f():\n    import nerfexp\n")
    assert imported_modules(script) == {"a.b", "c", "nerfexp.x", "nerfexp"}


@pytest.mark.parametrize("script", [s for s in SCRIPTS if s.suffix == ".py"], ids=lambda s: s.stem)
def test_each_python_script_loads_from_where_it_lies(script, monkeypatch):
    """Its module-level code (the imports, of nerfexp and of its neighbours, and the constants) runs as
    ``python benchmarks/FOLDER/NAME.py`` runs it, its own folder first on the path; what runs under
    ``__name__ == "__main__"`` does not. A script of another tool's environment is skipped (the module's docstring)."""
    if other := environment(script):
        pytest.skip(f"{script.relative_to(REPO)} runs in {other}'s own environment, whose imports this one lacks")
    monkeypatch.syspath_prepend(str(script.parent))
    before = set(sys.modules)
    try:
        found = runpy.run_path(str(script), run_name="benchmark_import_check")
    finally:  # the neighbours it imported by bare name (hashgrid, precision) leave with it
        for name in set(sys.modules) - before:
            if script.parent in Path(getattr(sys.modules[name], "__file__", None) or "/").parents:
                del sys.modules[name]
    assert found["__doc__"], f"{script.relative_to(REPO)}: no docstring saying what it answers"


@pytest.mark.parametrize("script", [s for s in SCRIPTS if s.suffix == ".py" and environment(s)], ids=lambda s: s.stem)
def test_a_script_of_another_environment_imports_nothing_of_nerfexp(script):
    ours = sorted(name for name in imported_modules(script) if name.split(".")[0] == "nerfexp")
    assert not ours, f"{script.relative_to(REPO)} runs in {environment(script)}'s environment, yet imports {ours}"


@pytest.mark.parametrize("script", [s for s in SCRIPTS if s.suffix == ".sh"], ids=lambda s: s.stem)
def test_each_shell_script_parses(script):
    done = subprocess.run(["bash", "-n", str(script)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
