"""nerfexp-report says once, below its table, which runs shared their machine and whether the runs come from several
machines, and then compares by time only what may be (run directories written by hand with known other_load values
and machines)."""

import csv
import json
from pathlib import Path

import pytest

from nerfexp.commands.report import main
from nerfexp.rundir.records import SHARED_LOAD
from tests.helpers import make_run


def with_load(run: Path, load: float | None) -> Path:
    """``run``'s results.json with ``other_load`` set (None: left out, as an earlier nerfexp's)."""
    results = json.loads((run / "results.json").read_text())
    if load is not None:
        results.update(other_load=load, cpu_time_s=50.0, cpus=2)
    (run / "results.json").write_text(json.dumps(results))
    return run


def sweep(root: Path, loads: dict[str, float | None], hosts: dict[str, str] | None = None) -> Path:
    """Two variants of two seeds each, run ``name`` with others' load ``loads[name]`` on host ``hosts[name]``
    (lab-pc by default), each tested at steps 10 and 20."""
    for i, (name, load) in enumerate(loads.items()):
        encoding, seed = ("posenc", "hashgrid")[i // 2], i % 2
        time_s = 100.0 + 10 * i
        budgets = [(10, time_s / 2, 18.0 + i, 0.7), (20, time_s, 20.0 + i, 0.8)]
        with_load(make_run(root, name, [f"encoding={encoding}", f"seed={seed}"], test_budgets=budgets,
                           host=(hosts or {}).get(name)), load)
    return root


def report(root: Path, capsys) -> tuple[str, str]:
    main([str(root), "--reference", "encoding=posenc"])
    return (root / "report.md").read_text(), capsys.readouterr().err


def time_rows(root: Path) -> list[dict]:
    with open(root / "report_budgets.csv") as file:
        return [row for row in csv.DictReader(file) if row["kind"] == "time"]


def test_runs_that_shared_their_machine_are_named_once_below_the_table(tmp_path, capsys):
    root = sweep(tmp_path / "sweep", {"0": 0.0, "1": 0.1, "2": SHARED_LOAD + 1.0, "3": None})
    text, err = report(root, capsys)
    lines = [line for line in text.splitlines() if "finished runs shared their machine" in line]
    assert len(lines) == 1 and text.count(f"`{root / '2'}`") == 1  # the caveat once, the run named once
    (line,) = lines
    assert line.startswith("1 of the 4 finished runs shared their machine") and f"`{root / '2'}` (1.25)" in line
    assert all(f"`{root / name}`" not in line for name in "013")  # below the threshold, or not measured
    assert "encoding=hashgrid compared with others by step only" in line
    head = text.split("\n## ")[0]  # the table and what it needs said, before the first section
    assert line in head and head.index("| encoding=") < head.index(line)  # said below the table, not above it
    assert [line.removeprefix("nerfexp-report: ") for line in err.splitlines() if "runs shared" in line] == lines
    # the variant with the shared run is not ranked by time, and says why in a word; the other is
    equal = text.split("## At equal training time")[1].split("\n## ")[0]
    assert "1. encoding=posenc (" in equal and "encoding=hashgrid (" not in equal
    assert equal.count("Not ranked, compared by step only (the note on times, below the table, says why): "
                       "encoding=hashgrid.") == 1
    assert time_rows(root) == []  # the only variant compared with the reference is the untimed one


def test_where_every_run_shared_its_machine_the_caveat_gives_their_number_and_loads_not_every_path(tmp_path, capsys):
    root = sweep(tmp_path / "sweep", {"0": 1.5, "1": SHARED_LOAD + 0.01, "2": 2.0, "3": 1.0})
    text, err = report(root, capsys)
    (line,) = [line for line in text.splitlines() if "shared their machine" in line]
    assert line == ("All 4 finished runs shared their machine (other processes kept 0.26 to 2.00 CPUs busy on average "
                    "while they trained, more than 0.25): their times, in the table and the plots, are partly their "
                    "neighbours', so no variant is compared with another by time (by step only).")
    assert line in text.split("\n## ")[0] and all(f"`{root / name}`" not in text for name in "0123")
    assert "No ranking at equal training time" in text and time_rows(root) == []
    assert [line.removeprefix("nerfexp-report: ") for line in err.splitlines() if "runs shared" in line] == [line]


def test_runs_at_or_below_the_threshold_or_that_did_not_measure_get_no_caveat(tmp_path, capsys):
    root = sweep(tmp_path / "sweep", {"0": SHARED_LOAD, "1": 0.0, "2": None, "3": 0.2})
    text, err = report(root, capsys)
    assert "shared their machine" not in text and "runs shared" not in err
    assert "## At equal training time\n\nWhat is best for a given time" in text and time_rows(root) != []


@pytest.mark.parametrize("hosts", [{"2": "gpu-b", "3": "gpu-b"}, {"1": "gpu-b"}])
def test_runs_from_several_machines_are_said_so_once_and_never_compared_by_time(tmp_path, capsys, hosts):
    # the second variant's runs on another machine, or one seed of the first: either way, times differ by machine
    root = sweep(tmp_path / "sweep", dict.fromkeys("0123", 0.0), hosts)
    text, err = report(root, capsys)
    lines = [line for line in text.splitlines() if "come from 2 machines" in line]
    assert len(lines) == 1 and "gpu-b: CPU" in lines[0] and "lab-pc: CPU" in lines[0]
    assert lines[0] in text.split("\n## ")[0] and text.count("gpu-b") == 1  # below the table, the machines once
    assert "No ranking at equal training time" in text and "**At " not in text  # not ranked after being said
    assert "at the pair's shortest run's total" not in text and time_rows(root) == []
    assert [line.removeprefix("nerfexp-report: ") for line in err.splitlines() if "come from" in line] == lines
