"""nerfexp-report says, in one line per comparison by time, which of the runs it compares shared their machine
(run directories written by hand with known other_load values)."""

import json
from pathlib import Path

from nerfexp.commands.report import main
from nerfexp.report.shared_machines import TIME_COMPARISONS
from nerfexp.rundir.records import SHARED_LOAD
from tests.helpers import make_run


def with_load(run: Path, load: float | None) -> Path:
    """``run``'s results.json with ``other_load`` set (None: left out, as an earlier nerfexp's)."""
    results = json.loads((run / "results.json").read_text())
    if load is not None:
        results.update(other_load=load, cpu_time_s=50.0, cpus=2)
    (run / "results.json").write_text(json.dumps(results))
    return run


def sweep(root: Path, loads: dict[str, float | None]) -> Path:
    """Two variants of two seeds each, run ``name`` with others' load ``loads[name]``."""
    for i, (name, load) in enumerate(loads.items()):
        encoding, seed = ("posenc", "hashgrid")[i // 2], i % 2
        with_load(make_run(root, name, [f"encoding={encoding}", f"seed={seed}"], time_s=100.0 + 10 * i), load)
    return root


def report(root: Path, capsys) -> tuple[str, str]:
    main([str(root)])
    return (root / "report.md").read_text(), capsys.readouterr().err


def test_one_line_per_time_comparison_names_the_runs_that_shared_their_machine(tmp_path, capsys):
    root = sweep(tmp_path / "sweep", {"0": 0.0, "1": SHARED_LOAD + 1.0, "2": 0.1, "3": None})
    text, err = report(root, capsys)
    lines = [line for line in text.splitlines() if "shared their machine" in line]
    assert len(lines) == len(TIME_COMPARISONS)
    for comparison, line in zip(TIME_COMPARISONS, lines):
        assert line.startswith(comparison) and "1 of its 4 runs" in line and "not the components' own" in line
        assert f"`{root / '1'}` (1.25)" in line  # the run above the threshold, with its load
        assert all(f"`{root / name}`" not in line for name in "023")  # below it, or not measured
    assert [line.removeprefix("nerfexp-report: ") for line in err.splitlines() if "shared" in line] == lines


def test_runs_at_or_below_the_threshold_or_that_did_not_measure_get_no_line(tmp_path, capsys):
    root = sweep(tmp_path / "sweep", {"0": SHARED_LOAD, "1": 0.0, "2": None, "3": 0.2})
    text, err = report(root, capsys)
    assert "shared their machine" not in text and "shared" not in err
