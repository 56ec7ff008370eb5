"""nerfexp-report per budget (issue 52): variants against the reference at each step their runs were tested at and
at matched training times, the verdict's words where it depends on the budget, and the ranking at equal training
time; run directories written by hand with known test scores, the intervals recomputed here with numpy and scipy."""

import csv
import json
import math
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from scipy import stats

from nerfexp.commands.report import main
from nerfexp.report.budgets import (
    Budget,
    budget_words,
    equal_time,
    equal_times,
    run_budgets,
    score_at_time,
    step_differences,
    time_differences,
)
from nerfexp.report.comparison import Difference
from nerfexp.report.folder import write_report
from nerfexp.report.runs import find_runs, read_run
from nerfexp.report.variants import group_variants, reference_variant
from tests.helpers import make_run
from tests.report.budget_runs import REFERENCE, WORSE_EARLY, budget_sweep


def read_rows(path: Path) -> list[dict]:
    with open(path) as file:
        return list(csv.DictReader(file))


def t_interval(values) -> tuple[float, float, float]:
    """(mean, low, high) of ``values``' mean, the 95% interval from scipy's Student's t."""
    values = np.asarray(values, dtype=np.float64)
    low, high = stats.t.interval(0.95, len(values) - 1, loc=values.mean(), scale=stats.sem(values))
    return values.mean(), low, high


def variants_of(root: Path, reference: str):
    variants = group_variants(find_runs([root]))
    return {v.label: v for v in variants}, reference_variant(variants, reference)


def test_per_step_differences_and_intervals_match_scipys(tmp_path):
    root = budget_sweep(tmp_path)
    write_report([root], root, reference="encoding=a")
    rows = read_rows(root / "report_budgets.csv")
    steps = {float(row["budget"]): row for row in rows if (row["kind"], row["metric"]) == ("step", "psnr")}
    assert sorted(steps) == [500, 1500]
    for i, step in enumerate((500, 1500)):
        mean, low, high = t_interval([WORSE_EARLY[seed][i] for seed in range(3)])
        row = steps[step]
        assert (row["variant"], row["reference"], row["n"]) == ("encoding=b", "encoding=a", "3")
        assert [float(row[k]) for k in ("diff", "low", "high")] == pytest.approx([mean, low, high], abs=1e-9)
    assert steps[500]["verdict"] == "worse" and steps[1500]["verdict"] == "not resolved with 3 seeds"
    ssim = [row for row in rows if (row["kind"], row["metric"]) == ("step", "ssim")]
    assert [float(row["diff"]) for row in ssim] == pytest.approx([0.0, 0.0])  # b's SSIM is a's
    # the same from the library, and the report's one row per variant carries the words
    variants, reference = variants_of(root, "encoding=a")
    differences = step_differences(variants["encoding=b"], reference)
    assert list(differences) == [500, 1500] and differences[500].mean == pytest.approx(-1.0)
    table = {row["variant"]: row for row in read_rows(root / "report.csv")}
    words = "depends on the budget: worse at 500 steps, not resolved at 1,500"
    assert table["encoding=b"]["budget_verdict"] == words and table["encoding=b"]["verdict"].startswith("not resolved")
    report = (root / "report.md").read_text()
    assert f"| not resolved with 3 seeds ({words}) |" in report  # the verdict column, the words after it
    mean, low, high = t_interval([WORSE_EARLY[s][0] for s in range(3)])
    assert f"| encoding=b | {mean:+.2f} [{low:+.2f}, {high:+.2f}] |" in report  # the Per budget table's first cell
    assert "## Per budget" in report and "## At equal training time" in report


def test_matched_time_interpolates_between_budgets_and_pairs_by_seed(tmp_path):
    # b trains at half a's time per step: at the same seconds it has more steps. Both are linear in time between
    # budgets, so at a matched time t each run's score is its line's value there, computed here by hand.
    root = budget_sweep(tmp_path, time_scale=0.5)
    variants, reference = variants_of(root, "encoding=a")
    b = variants["encoding=b"]

    def line(budgets, t):  # the run's score at t by np.interp, an independent linear interpolation
        return float(np.interp(t, [x[1] for x in budgets], [x[2] for x in budgets]))

    times = [40.0, 60.0, 72.0, 73.0, 100.0]  # b's runs end at 75, 78, 72 s; a's first tests at 50, 52, 48 s
    differences = time_differences(b, reference, times)
    assert list(differences) == [60.0, 72.0]  # 40 s: before a's first tests; 73 s and on: after b's seed 2 ended
    for t, d in differences.items():
        expected = [line([(s, x * 0.5, p + o, q) for (s, x, p, q), o in zip(REFERENCE[seed], WORSE_EARLY[seed])], t)
                    - line(REFERENCE[seed], t) for seed in range(3)]
        mean, low, high = t_interval(expected)
        assert (d.n, d.mean, *d.interval) == pytest.approx((3, mean, low, high), abs=1e-9)


@pytest.mark.parametrize("t", [10.0, 12.5, 29.0, 30.0, 50.0, 69.9, 70.0])
def test_a_runs_score_at_a_time_is_the_linear_function_between_its_budgets(t):
    # budgets on the line psnr = 10 + 0.05 t, ssim = 0.5 + 0.004 t, at 10, 30 and 70 s: interpolation gives the line
    budgets = [Budget(step, time_s, 10 + 0.05 * time_s, 0.5 + 0.004 * time_s) for step, time_s in
               ((100, 10.0), (300, 30.0), (700, 70.0))]
    assert score_at_time(budgets, t) == pytest.approx(10 + 0.05 * t, abs=1e-12)
    assert score_at_time(budgets, t, "ssim") == pytest.approx(0.5 + 0.004 * t, abs=1e-12)


def test_no_score_is_extrapolated_before_the_first_budget_or_after_the_end_nor_from_a_nan():
    budgets = [Budget(100, 10.0, 20.0, 0.5), Budget(300, 30.0, 24.0, 0.6), Budget(700, 70.0, math.nan, 0.7)]
    assert score_at_time(budgets, 9.999) is None and score_at_time(budgets, 70.001) is None
    assert score_at_time(budgets, 20.0) == pytest.approx(22.0)  # halfway: (20 + 24) / 2
    assert score_at_time(budgets, 40.0) is None  # between 24 dB and a score that is not one
    assert score_at_time([Budget(5, 10.0, 20.0, 0.5)], 10.0) == 20.0 and score_at_time([], 10.0) is None


def diff(mean: float, half: float | None, n: int = 3) -> Difference:
    return Difference(mean, n, None if half is None else (mean - half, mean + half))


@pytest.mark.parametrize(("differences", "words"), [
    # the same verdict throughout, moving less than the last half-width: nothing to say
    ({500: diff(-1.0, 0.3), 1500: diff(-1.2, 0.3)}, ""),
    ({500: diff(0.1, 0.3), 1500: diff(0.0, 0.3)}, ""),
    ({1500: diff(-1.0, 0.3)}, ""),  # one budget
    # a resolved difference changes sign
    ({500: diff(1.0, 0.3), 1500: diff(-0.6, 0.4)},
     "depends on the budget: better at 500 steps, worse at 1,500; still moving: -1.60 dB from 500 to 1,500 steps, "
     "more than the interval's half-width (0.40)"),
    # resolved only at some budgets, consecutive equal verdicts merged
    ({250: diff(-1.0, 0.3), 500: diff(-1.1, 0.3), 1000: diff(-0.9, 1.2)},
     "depends on the budget: worse at 250 and 500 steps, not resolved at 1,000"),
    ({250: diff(0.0, 0.3), 500: diff(0.5, 0.3), 750: diff(0.6, 0.3), 1000: diff(0.2, 0.3)},
     "depends on the budget: not resolved at 250 steps, better at 500 and 750, not resolved at 1,000; still moving: "
     "-0.40 dB from 750 to 1,000 steps, more than the interval's half-width (0.30)"),
    # still moving: the same verdict, but the last step moved it by more than its interval's half-width
    ({750: diff(0.5, 0.3), 1500: diff(1.02, 0.31)},
     "still moving: +0.52 dB from 750 to 1,500 steps, more than the interval's half-width (0.31)"),
    # steps without a pair say nothing; without an interval at the last step, no "still moving"
    ({500: Difference(math.nan, 0, None), 1500: diff(-1.0, 0.3)}, ""),
    ({500: diff(0.0, 0.3), 1500: diff(2.0, None, n=1)}, ""),
])
def test_budget_words(differences, words):
    assert budget_words(differences) == words


def test_runs_that_shared_their_machine_are_compared_by_step_only_and_named(tmp_path):
    root = budget_sweep(tmp_path, time_scale=0.5, other_load={"b1": 1.5})
    write_report([root], root, reference="encoding=a")
    rows = read_rows(root / "report_budgets.csv")
    assert {row["kind"] for row in rows} == {"step"}  # b's one shared run costs every comparison of b by time
    report = (root / "report.md").read_text()
    line = next(line for line in report.splitlines() if "compared with others by step only" in line)
    assert line.startswith("1 of the 6 finished runs shared their machine") and f"`{root / 'b1'}` (1.50)" in line
    assert f"`{root / 'b0'}`" not in line and line.endswith("and encoding=b compared with others by step only.")
    equal = report.split("## At equal training time")[1].split("##")[0]
    assert "encoding=b (" not in equal and "encoding=a (" in equal  # ranked: a only
    assert "Not ranked, compared by step only (the note on times, below the table, says why): encoding=b." in equal
    # the same sweep with nobody beside the runs is compared by time too
    plain = budget_sweep(tmp_path / "plain", time_scale=0.5)
    write_report([plain], plain, reference="encoding=a")
    assert {row["kind"] for row in read_rows(plain / "report_budgets.csv")} == {"step", "time"}
    assert "compared by step only" not in (plain / "report.md").read_text()


def linear_runs(root: Path, label: str, start: float, slope: float, seconds: list[float], noise=(0.0, 0.1, -0.1)):
    """Three seeds of ``label`` tested at ``seconds`` (steps 100, 200, ...), test PSNR start + slope t + noise."""
    for seed, offset in enumerate(noise):
        make_run(root, f"{label}{seed}", [f"encoding={label}", f"seed={seed}"],
                 test_budgets=[(100 * (i + 1), t, start + slope * t + offset, 0.8) for i, t in enumerate(seconds)])


def test_equal_time_ranks_at_the_fastest_variants_times(tmp_path):
    # fast: tested at 15, 30, 60 s (the fastest: its times are the table's); slow: at 70, 140, 280 s, a line far
    # above, first tested after every one of them; mid: at 10, 40, 80 s, fast's line with other noise, above fast's
    # in every seed (by 0.05, 0.1, 0.08 dB: resolved, paired by seed).
    linear_runs(tmp_path, "fast", 20.0, 0.1, [15.0, 30.0, 60.0])
    linear_runs(tmp_path, "slow", 30.0, 0.1, [70.0, 140.0, 280.0])
    linear_runs(tmp_path, "mid", 20.0, 0.1, [10.0, 40.0, 80.0], noise=(0.05, 0.2, -0.02))
    variants = group_variants(find_runs([tmp_path]))
    at = {t: equal_time(variants, t) for t in (15.0, 30.0, 60.0)}
    for t, table in at.items():
        # mid's mean at t: 20 + 0.1 t + mean(0.05, 0.2, -0.02); fast's: 20 + 0.1 t + mean(0, 0.1, -0.1)
        assert [(label, n) for label, _, n in table.ranked] == [("encoding=mid", 3), ("encoding=fast", 3)]
        assert [mean for _, mean, _ in table.ranked] == pytest.approx(
            [20 + 0.1 * t + np.mean([0.05, 0.2, -0.02]), 20 + 0.1 * t + np.mean([0.0, 0.1, -0.1])])
        assert table.uncovered == [("encoding=slow", f"first test after {t:,.0f} s (at 70 s)")]
    # mid - fast per seed: 0.05, 0.1, 0.08: resolved above (not one group); two equal lines would be one group
    assert at[30.0].groups == [["encoding=mid"], ["encoding=fast"]]
    write_report([tmp_path], tmp_path)
    report = (tmp_path / "report.md").read_text()
    assert "**At 30 s, ranked:**\n\n1. encoding=mid (23.08 dB, 3 runs)\n2. encoding=fast (23.00 dB, 3 runs)\n" \
           "- encoding=slow: first test after 30 s (at 70 s)" in report
    assert "the variants at the fastest one's (`encoding=fast`) budgets' times" in report


def test_equal_times_are_where_every_run_of_the_fastest_variant_has_a_score(tmp_path):
    # fast's seeds tested at 10/20/40, 14/30/50 and 12/25/45 s: mean budget times 12, 25 and 45 s; a time before
    # the slowest seed's first test (14 s) or past the quickest seed's end (40 s) would leave a seed of its own out
    for seed, seconds in enumerate([(10.0, 20.0, 40.0), (14.0, 30.0, 50.0), (12.0, 25.0, 45.0)]):
        make_run(tmp_path, f"fast{seed}", ["encoding=fast", f"seed={seed}"],
                 test_budgets=[(100 * (i + 1), t, 20.0 + 0.1 * t, 0.8) for i, t in enumerate(seconds)])
    linear_runs(tmp_path, "slow", 20.0, 0.1, [15.0, 60.0, 120.0])
    fastest, times = equal_times(group_variants(find_runs([tmp_path])))
    assert fastest.label == "encoding=fast" and times == pytest.approx([14.0, 25.0, 40.0])
    assert [n for _, _, n in equal_time([fastest], 14.0).ranked] == [3]


def test_variants_the_seeds_cannot_tell_apart_at_a_time_share_a_line(tmp_path):
    linear_runs(tmp_path, "fast", 20.0, 0.1, [15.0, 30.0, 60.0], noise=(0.0, 0.1, -0.1))
    linear_runs(tmp_path, "twin", 20.0, 0.1, [15.0, 30.0, 60.0], noise=(0.1, 0.0, -0.05))  # per seed +0.1, -0.1, +0.05
    variants = group_variants(find_runs([tmp_path]))
    assert equal_time(variants, 30.0).groups == [["encoding=twin", "encoding=fast"]]


def test_runs_of_an_earlier_nerfexp_have_one_budget_their_end(tmp_path):
    for seed, (a, b) in enumerate([(20.0, 21.0), (22.0, 23.5), (24.0, 24.5)]):
        make_run(tmp_path, f"a{seed}", ["encoding=a", f"seed={seed}"], psnr=a, time_s=100.0)
        make_run(tmp_path, f"b{seed}", ["encoding=b", f"seed={seed}"], psnr=b, time_s=90.0)
    run = read_run(tmp_path / "a1")
    assert "test_budgets" not in run.results and run_budgets(run) == [Budget(20, 100.0, 22.0, 0.8)]
    write_report([tmp_path], tmp_path, reference="encoding=a")
    rows = read_rows(tmp_path / "report_budgets.csv")
    step = [row for row in rows if (row["kind"], row["metric"]) == ("step", "psnr")]
    mean, low, high = t_interval([1.0, 1.5, 0.5])
    assert [(row["budget"], row["n"]) for row in step] == [("20", "3")]
    assert [float(step[0][k]) for k in ("diff", "low", "high")] == pytest.approx([mean, low, high])
    # times: b's end at 90 s; a's first (and only) test at 100 s: no time both have
    assert [row for row in rows if row["kind"] == "time"] == []
    table = {row["variant"]: row for row in read_rows(tmp_path / "report.csv")}
    assert table["encoding=b"]["budget_verdict"] == ""
    report = (tmp_path / "report.md").read_text()
    assert "- encoding=a: first test after 90 s (at 100 s)" in report


def test_the_paper_order_names_the_budget_it_used(tmp_path):
    rows = {"complete": 28.0, "no_posenc": 29.0}
    for row, psnr in rows.items():
        for seed in range(2):
            make_run(tmp_path / "agree", f"{row}{seed}", [f"ablation={row}", f"seed={seed}"], choices={"ablation": row},
                     test_budgets=[(250, 10.0, psnr - 2, 0.7), (1000, 40.0, psnr + seed, 0.8)])
            make_run(tmp_path / "mixed", f"{row}{seed}", [f"ablation={row}", f"seed={seed}"], psnr=psnr + seed,
                     choices={"ablation": row}, test_budgets=None if seed else [(1000, 40.0, psnr, 0.8)])
    write_report([tmp_path / "agree"], tmp_path / "agree")
    assert "Compared at the end of training, at 1,000 steps" in (tmp_path / "agree" / "report.md").read_text()
    write_report([tmp_path / "mixed"], tmp_path / "mixed")  # one seed ended at 1,000 steps, one at 20
    assert "Compared at the end of training, at each run's last step" in (tmp_path / "mixed" / "report.md").read_text()


def budgets_of(run: Path) -> list[dict]:
    return json.loads((run / "results.json").read_text())["test_budgets"]


# a change to a run's test_budgets (a function of the list), and how the report names it
DAMAGE = [
    (lambda b: [{**b[0], "step": "500"}, b[1]], "key 'test_budgets', item 0: key 'step' is '500': expected a whole"),
    (lambda b: [{**b[0], "step": 0}, b[1]], "item 0: key 'step' is 0: expected a whole number in [1, 2^63 - 1]"),
    (lambda b: [b[0], {**b[1], "evaluations": math.nan}], "item 1: key 'evaluations' is nan: expected a finite"),
    (lambda b: [b[0], {**b[1], "test_psnr": "25"}], "item 1: key 'test_psnr' is '25': expected a number in [0"),
    (lambda b: [b[0], {**b[1], "test_lpips": -1.0}], "item 1: key 'test_lpips' is -1.0: expected a finite number >= 0"),
    (lambda b: [{k: v for k, v in b[0].items() if k != "score_s"}, b[1]], "item 0: no key 'score_s'"),
    (lambda b: [b[1], b[0]], "item 1: step 500 at 50.0 s after step 1500 at 150.0 s: expected steps increasing"),
    (lambda b: [b[0], {**b[1], "train_time_s": 40.0}], "item 1: step 1500 at 40.0 s after step 500 at 50.0 s"),
    (lambda b: [], "key 'test_budgets' is []: expected a list of one or more mappings"),
    (lambda b: [b[0], 7], "key 'test_budgets' is [{"),
    (lambda b: "all", "key 'test_budgets' is 'all': expected a list of one or more mappings"),
]


@pytest.mark.parametrize(("change", "says"), DAMAGE, ids=[says[:40] for _, says in DAMAGE])
def test_test_budgets_not_as_nerfexp_writes_them_make_the_run_damaged(tmp_path, change, says):
    run = make_run(tmp_path, "0", ["seed=0"], test_budgets=REFERENCE[0])
    results = json.loads((run / "results.json").read_text())
    (run / "results.json").write_text(json.dumps({**results, "test_budgets": change(budgets_of(run))}))
    read = read_run(run)
    assert (read.state, read.overrides, read.results) == ("damaged", ["seed=0"], None)
    assert read.detail.startswith("results.json: ") and says in read.detail and "\n" not in read.detail, read.detail


def test_budget_scoring_seconds_not_a_number_make_the_run_damaged_and_are_said_when_they_are(tmp_path):
    run = make_run(tmp_path / "odd", "0", ["seed=0"], test_budgets=REFERENCE[0])
    results = json.loads((run / "results.json").read_text())
    (run / "results.json").write_text(json.dumps({**results, "budget_scoring_s": -1.0}))
    assert read_run(run).detail == ("results.json: key 'budget_scoring_s' is -1.0: expected a finite number >= 0 "
                                    "and <= 2^63 - 1")
    root = budget_sweep(tmp_path / "sweep")
    write_report([root], root, reference="encoding=a")  # each run scored one budget before its end, in 0.5 s
    assert "Scoring the budgets before the end took 0.5 s a run on average" in (root / "report.md").read_text()


def test_the_difference_plot_and_the_paretos_budget_points_are_drawn(tmp_path):
    root = budget_sweep(tmp_path / "budgets", time_scale=0.5)
    write_report([root], root, reference="encoding=a")
    # the same runs' ends only (as an earlier nerfexp's): the Pareto plot without the budgets' points
    ends = tmp_path / "ends"
    for seed, budgets in REFERENCE.items():
        (step, t, p, s), d = budgets[-1], WORSE_EARLY[seed][-1]
        make_run(ends, f"a{seed}", ["encoding=a", f"seed={seed}"], test_budgets=[(step, t, p, s)])
        make_run(ends, f"b{seed}", ["encoding=b", f"seed={seed}"], test_budgets=[(step, t * 0.5, p + d, s)])
    write_report([ends], ends, reference="encoding=a")
    for folder in (root, ends):
        for name in ("difference_vs_time.png", "pareto.png"):
            image = iio.imread(folder / name)
            assert image.shape[:2] == (500, 800) and image.std() > 0, (folder, name)  # 8 x 5 inches at 100 dpi
    assert not np.array_equal(iio.imread(root / "pareto.png"), iio.imread(ends / "pareto.png"))
    # with matched times the difference plot has a curve and its band; without (no shared time), only its axes
    assert not np.array_equal(iio.imread(root / "difference_vs_time.png"), iio.imread(ends / "difference_vs_time.png"))
    assert [row for row in read_rows(ends / "report_budgets.csv") if row["kind"] == "time"] == []
    html = (root / "report.html").read_text()
    assert '<img src="difference_vs_time.png"' in html and "<h2>Per budget</h2>" in html
    assert "<h2>At equal training time</h2>" in html


def test_a_report_of_runs_of_10001_budgets_takes_seconds_and_says_each_step_of_its_work(tmp_path, capsys):
    # b 0.5 dB under a at every one of 10,001 budgets (steps 1, 2, ..., seconds 1, 2, ...): every step and every
    # matched time compared. Each budget was once looked up by a walk over every budget of every run: hours of work
    n = 10_001
    for label, offset in (("a", 0.0), ("b", -0.5)):
        make_run(tmp_path, label, [f"encoding={label}", "seed=0"],
                 test_budgets=[(i + 1, i + 1.0, 20.0 + offset + i / n, 0.8) for i in range(n)])
    started = time.process_time()
    main([str(tmp_path), "--reference", "encoding=a"])
    assert time.process_time() - started < 120  # CPU seconds of this process: a few here
    assert capsys.readouterr().err.splitlines() == [
        f"nerfexp-report: reading the runs under {tmp_path}",
        "nerfexp-report: comparing 2 variants; runs: 2 (2 finished); 20,002 test budgets",
        "nerfexp-report: drawing the plots",
        "nerfexp-report: writing the pictures of 0 test views",
        "nerfexp-report: writing the page",
        f"2 variants; report in {tmp_path / 'report.md'} and {tmp_path / 'report.html'}"]
    rows = read_rows(tmp_path / "report_budgets.csv")
    steps = [row for row in rows if (row["kind"], row["metric"]) == ("step", "psnr")]
    assert [int(row["budget"]) for row in steps] == list(range(1, n + 1))
    assert all(float(row["diff"]) == pytest.approx(-0.5) and row["n"] == "1" for row in steps)
