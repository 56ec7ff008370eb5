"""README.md as the door to nerfexp, not the house: short (at most 150 lines, no table cell over 200 characters),
the two commands a newcomer runs as CI runs them, a map of docs/ that names every guide (as docs/README.md does),
and every command line it shows one that nerfexp takes (``tests/command_lines.py``)."""

import re

import pytest

from tests.command_lines import SCRIPTS, refusal
from tests.helpers import REPO
from tests.markdown import command_lines, long_cells

README = (REPO / "README.md").read_text()
MOST_LINES = 150
GUIDES = sorted(path.name for path in (REPO / "docs").glob("*.md") if path.name != "README.md")
LINK = re.compile(r"\]\(([^)#\s]+)")


def test_long_cells_are_found():
    assert long_cells(f"| a | b |\n|---|---|\n| {'x' * 201} | y |\n") == ["x" * 201]
    assert long_cells(f"| a |\n|---|\n| {'x' * 200} |\n") == []


def test_the_readme_is_short_and_its_tables_cells_too():
    assert len(README.splitlines()) <= MOST_LINES
    assert not long_cells(README)


def test_the_two_commands_are_there_and_pin_the_torch_ci_installs():
    lines = README.splitlines()
    assert "    pip install torch==2.13.0 -e . && nerfexp" in lines  # installs, and runs the default experiment
    assert "    bash .ci/run" in lines  # installs, and runs the tests
    (pinned,) = set(re.findall(r"torch==([\d.]+)", (REPO / ".ci" / "run").read_text()))
    assert set(re.findall(r"torch==([\d.]+)", README)) == {pinned}


@pytest.mark.parametrize("page, prefix", [("README.md", "docs/"), ("docs/README.md", "")])
def test_the_map_of_the_docs_names_every_guide(page, prefix):
    linked = set(LINK.findall((REPO / page).read_text()))
    assert not [guide for guide in GUIDES if prefix + guide not in linked]


@pytest.mark.parametrize("command", command_lines(README, set(SCRIPTS)), ids=" ".join)
def test_every_command_line_it_shows_is_one_nerfexp_takes(command):
    assert refusal(command) is None


def test_a_command_line_nerfexp_refuses_is_found():
    assert "scale.lr=-1" in refusal(["nerfexp", "scale.lr=-1"])  # a value out of its domain
    assert "posenk" in refusal(["nerfexp", "-m", "encoding=posenc,posenk"])  # a sweep's second job
    assert "add -m" in refusal(["nerfexp", "seed=0,1"])  # a sweep in a single run
    assert refusal(["nerfexp", "+sweeps=smoke", "seed=0,1"]) is None  # a sweep file's runs are a sweep's
    assert "ablation" in refusal(["nerfexp", "+sweeps=smoke", "encoding=hashgrid"])  # the sweep file's rows
    assert "--bogus" in refusal(["nerfexp-report", "DIR", "--bogus"])
