"""A results.json that contradicts itself (nerfexp.rundir.records.relations_problem): nerfexp's own runs keep every
relation; one broken, in a real run's results.json or in a sweep's, makes the run damaged with one line naming the
keys and the relation, and the report leaves it out of every comparison: its tables, rankings and plots are those
of the same sweep without the run."""

import copy
import csv
import json
import shutil
from collections.abc import Callable
from pathlib import Path

import imageio.v3 as iio
import pytest

from nerfexp.report.folder import write_report
from nerfexp.report.runs import read_run
from nerfexp.rundir.records import relations_problem
from tests.report.budget_runs import budget_sweep


def end(results: dict) -> dict:
    return results["test_budgets"][-1]


def last(results: dict) -> str:
    """How a message names the last budget, the end."""
    return f"key 'test_budgets', item {len(results['test_budgets']) - 1}, the last, says"


def between(results: dict) -> int:
    """A step between the last budget before the end and the end."""
    return (results["test_budgets"][-2]["step"] + results["steps"]) // 2


def views_off_by_one(results: dict) -> None:
    """Per-view PSNRs each 1 dB above those the headline is the mean of (one view where the run has none)."""
    results.setdefault("test_views", [0])
    results.setdefault("test_ssim_per_view", [results["test_ssim"]])
    results["test_psnr_per_view"] = [psnr + 1.0 for psnr in results.get("test_psnr_per_view", [results["test_psnr"]])]


# Each relation nerfexp keeps in a results.json, broken: (the change, the message naming it, from the results before)
BREAKS: dict[str, tuple[Callable[[dict], None], Callable[[dict], str]]] = {
    "the end scores 99 dB, the headline less": (
        lambda r: end(r).update(test_psnr=99.0),
        lambda r: f"{last(r)} test_psnr 99.0, but key 'test_psnr' is {r['test_psnr']!r}: expected the last budget to "
                  "be the run's end, with its headline numbers"),
    "the headline is 9.83 dB, the end more": (
        lambda r: r.update(test_psnr=9.83),
        lambda r: f"{last(r)} test_psnr {end(r)['test_psnr']!r}, but key 'test_psnr' is 9.83"),
    "the end's SSIM is not the headline's": (
        lambda r: end(r).update(test_ssim=end(r)["test_ssim"] / 2),
        lambda r: f"{last(r)} test_ssim {end(r)['test_ssim'] / 2!r}, but key 'test_ssim' is {r['test_ssim']!r}"),
    "LPIPS at the end only": (
        lambda r: end(r).update(test_lpips=0.25),
        lambda r: f"{last(r)} test_lpips 0.25, but key 'test_lpips' is {r.get('test_lpips')!r}"),
    "the end relabelled an earlier step": (
        lambda r: end(r).update(step=between(r)),
        lambda r: f"{last(r)} step {between(r)}, but key 'steps' is {r['steps']}"),
    "the end at another time": (
        lambda r: end(r).update(train_time_s=end(r)["train_time_s"] + 1.0),
        lambda r: f"{last(r)} train_time_s {end(r)['train_time_s'] + 1.0!r}, but key 'train_time_s' is "
                  f"{r['train_time_s']!r}"),
    "a budget after the run's last step": (
        lambda r: r.update(steps=end(r)["step"] - 1),
        lambda r: f"key 'test_budgets', item {len(r['test_budgets']) - 1} says step {end(r)['step']}, but the run "
                  f"ended at step {end(r)['step'] - 1} (key 'steps'): expected every budget within the run's steps"),
    "steps not increasing": (
        lambda r: r["test_budgets"][-2].update(step=end(r)["step"]),
        lambda r: f"key 'test_budgets', item {len(r['test_budgets']) - 1}: step {end(r)['step']} at "
                  f"{end(r)['train_time_s']!r} s after step {end(r)['step']} at"),
    "the training clock going back": (
        lambda r: r["test_budgets"][-2].update(train_time_s=end(r)["train_time_s"] + 1.0),
        lambda r: f"s after step {r['test_budgets'][-2]['step']} at {end(r)['train_time_s'] + 1.0!r} s: expected "
                  "steps increasing and training times never decreasing"),
    "the budgets' scoring seconds not their sum": (
        lambda r: r.update(budget_scoring_s=r["budget_scoring_s"] + 1.0),
        lambda r: f"key 'budget_scoring_s' is {r['budget_scoring_s'] + 1.0!r}, but the budgets before the end took "
                  f"{r['budget_scoring_s']!r} s (key 'test_budgets', their score_s): expected the sum"),
    "seconds per step not the quotient": (
        lambda r: r.update(time_per_step_s=r["time_per_step_s"] * 2),
        lambda r: f"key 'time_per_step_s' is {r['time_per_step_s'] * 2!r}, but key 'train_time_s' / max(1, key "
                  f"'steps') is {r['train_time_s']!r} / max(1, {r['steps']}) = "),
    "the headline not the mean of the views": (
        views_off_by_one,
        lambda r: f"key 'test_psnr' is {r['test_psnr']!r}, but the mean of key 'test_psnr_per_view' is "),
}


def broken(run: Path, name: str) -> str:
    """Break the relation ``BREAKS[name]`` in ``run``'s results.json; the message that names it."""
    change, says = BREAKS[name]
    results = json.loads((run / "results.json").read_text())
    edited = copy.deepcopy(results)
    change(edited)
    (run / "results.json").write_text(json.dumps(edited))
    return says(results)


def test_nerfexps_own_results_keep_every_relation(tiny_run):
    results = json.loads((tiny_run / "results.json").read_text())
    # budgets at 1/4 and 1/2 of its 60 steps, and the end; per-view scores of its test views: every relation applies
    assert [budget["step"] for budget in results["test_budgets"]] == [15, 30, 60] and results["steps"] == 60
    assert len(results["test_psnr_per_view"]) == len(results["test_views"]) > 1
    assert relations_problem(results) is None
    assert read_run(tiny_run).state == "finished"


@pytest.mark.parametrize("name", BREAKS)
def test_a_real_runs_results_that_contradict_themselves_make_it_damaged_naming_the_relation(tiny_run, tmp_path, name):
    run = tmp_path / "run"
    run.mkdir()
    for file in ("results.json", "status.json", "metrics.jsonl"):
        shutil.copy(tiny_run / file, run / file)
    says = broken(run, name)
    read = read_run(run)
    assert (read.state, read.results, read.budgets) == ("damaged", None, [])
    assert read.detail.startswith("results.json: key '") and says in read.detail, read.detail
    assert "\n" not in read.detail


def csv_rows(path: Path, leave_out: tuple[str, ...] = ()) -> list[dict]:
    with open(path) as file:
        return [{k: v for k, v in row.items() if k not in leave_out} for row in csv.DictReader(file)]


def compared(root: Path) -> dict:
    """What a report of ``root`` compares: report.csv's rows but the runs counted, report_budgets.csv, report.md
    from its ranking to the jobs not counted, and the plots' pixels."""
    report = (root / "report.md").read_text()
    return {"report.csv": csv_rows(root / "report.csv", leave_out=("runs",)),
            "report_budgets.csv": csv_rows(root / "report_budgets.csv"),
            "report.md": report[report.index("## Ranking"):report.index("## Jobs")],
            **{name: iio.imread(root / name).tolist()
               for name in ("psnr_vs_time.png", "pareto.png", "difference_vs_time.png")}}


@pytest.fixture(scope="module")
def without_the_run(tmp_path_factory) -> dict:
    """What the report of the budget sweep (reference a; b, 1 dB worse at 500 steps) compares without b's seed 0."""
    root = budget_sweep(tmp_path_factory.mktemp("without"))
    shutil.rmtree(root / "b0")
    write_report([root], root, reference="encoding=a")
    return compared(root)


@pytest.mark.parametrize("name", BREAKS)
def test_a_run_that_contradicts_itself_is_listed_as_damaged_and_in_no_comparison(tmp_path, without_the_run, name):
    root = budget_sweep(tmp_path)
    says = broken(root / "b0", name)
    write_report([root], root, reference="encoding=a")
    report = (root / "report.md").read_text()
    assert "Runs: 6 (5 finished, 1 damaged)" in report
    assert f"- `{root / 'b0'}` (encoding=b, seed=0): damaged: results.json: " in report and says in report
    assert compared(root) == without_the_run  # the tables, the rankings and the plots: as if it were not there
    assert "| encoding=b | 2/3 |" in report
