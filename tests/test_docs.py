"""The user's guide, docs/ and benchmarks/README.md as documentation: every relative link lands on a file (and a
heading, where it names one), and no page outside docs/results dates itself by a commit (measurements and their
commits live in docs/results and benchmarks/results; history lives in git)."""

import re
from pathlib import Path

import pytest

from tests.helpers import REPO

PAGES = sorted([REPO / "README.md", REPO / "benchmarks" / "README.md", *(REPO / "docs").rglob("*.md")])
GUIDES = sorted((REPO / "docs").glob("*.md"))  # docs/results/ holds measurements, which name their commits
LINK = re.compile(r"\]\(([^)\s]+)\)")
# a commit as git abbreviates it: 7 to 40 hexadecimal digits, with a letter and a digit among them
COMMIT = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")
DIGESTS = {"7be5be79", "df73285e"}  # the AlexNet weights' SHA-256 prefixes (torchvision's file name, lpips' file)


def heading_anchor(title: str) -> str:
    """A Markdown heading's anchor as GitHub makes it: lower case, punctuation but - and _ dropped, spaces -."""
    return re.sub(r"[^\w\- ]", "", title.strip().lower()).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    """The anchors of ``page``'s headings, those inside fenced code left out."""
    found, fenced = set(), False
    for line in page.read_text().splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and (heading := re.match(r"#+\s+(.*)", line)):
            found.add(heading_anchor(heading[1]))
    return found


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


def test_commit_pattern_finds_abbreviated_commits_only():
    assert COMMIT.findall("at commit 4e367d5, 2654435761 and 0.9743") == ["4e367d5"]


@pytest.mark.parametrize("page", GUIDES, ids=lambda p: p.name)
def test_no_guide_dates_itself_by_a_commit(page):
    assert set(COMMIT.findall(page.read_text())) <= DIGESTS
