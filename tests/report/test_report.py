"""nerfexp-report on hand-made run directories whose numbers are known, checked exactly."""

import csv
import json
import math
import os
import re
import socket
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import pytest

from nerfexp import manifest
from nerfexp.commands.report import main
from nerfexp.reading import UnreadableFile
from nerfexp.report.folder import write_report
from nerfexp.report.plots import mean_curve
from nerfexp.report.publications import PAPER_ABLATION
from nerfexp.report.runs import Run, find_runs, run_precision
from nerfexp.report.variants import group_variants
from nerfexp.rundir.layout import planned_jobs, process_start
from tests.helpers import digests, make_run


def dead_pid() -> int:
    """The id of a process that has exited (as a job killed by the system leaves behind)."""
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid


@pytest.fixture
def sweep(tmp_path):
    """Variant A: three seeds at 20, 22, 24 dB. Variant B: one finished (25 dB), one failed, one
    killed. Variant C: its only job still running (this test's own process)."""
    root = tmp_path / "sweep"
    for seed, (psnr, ssim, time_s) in enumerate([(20, 0.80, 90), (22, 0.85, 100), (24, 0.90, 110)]):
        make_run(root, f"{seed}", ["hierarchical=true", f"seed={seed}"], psnr=psnr, ssim=ssim, time_s=time_s)
    make_run(root, "3", ["hierarchical=false", "seed=0"], psnr=25.0, ssim=0.95, time_s=50)
    make_run(root, "4", ["hierarchical=false", "seed=1"], state="failed",
             error="NonFiniteError: step 7: the fine network's colour loss is nan")
    make_run(root, "5", ["hierarchical=false", "seed=2"], state="running", pid=dead_pid())
    make_run(root, "6", ["encoding=none", "seed=0"], state="running")
    return root


def read_csv(path: Path) -> list[dict]:
    with open(path) as file:
        return list(csv.DictReader(file))


def test_means_stds_and_unfinished_jobs_exactly(sweep):
    write_report([sweep], sweep)
    rows = {row["variant"]: row for row in read_csv(sweep / "report.csv")}
    assert list(rows) == ["hierarchical=false", "hierarchical=true", "encoding=none"]  # ranked by PSNR
    a, b, c = rows["hierarchical=true"], rows["hierarchical=false"], rows["encoding=none"]
    # 20, 22, 24: mean 22, sample std sqrt(((-2)^2 + 0 + 2^2) / 2) = 2; SSIM 0.85 +- 0.05; time 100 +- 10
    assert (a["runs"], a["finished"]) == ("3", "3")
    assert float(a["test_psnr_mean"]) == 22.0 and float(a["test_psnr_std"]) == 2.0
    assert math.isclose(float(a["test_ssim_mean"]), 0.85) and math.isclose(float(a["test_ssim_std"]), 0.05)
    assert float(a["train_time_s"]) == 100.0 and float(a["time_per_step_s"]) == 5.0
    # the failed and the killed job count as runs, not as results: one finished, std undefined
    assert (b["runs"], b["finished"], float(b["test_psnr_mean"])) == ("3", "1", 25.0)
    assert math.isnan(float(b["test_psnr_std"]))
    assert (c["runs"], c["finished"]) == ("1", "0") and math.isnan(float(c["test_psnr_mean"]))
    report = (sweep / "report.md").read_text()
    assert "| hierarchical=true | 3/3 | 22.00 ± 2.00 | 0.850 ± 0.050 | 100 |" in report
    assert "Runs: 7 (4 finished, 1 failed, 1 killed, 1 running)" in report
    assert "failed: NonFiniteError: step 7: the fine network's colour loss is nan" in report
    assert "killed: process" in report and f"running: on {socket.gethostname()}, process {os.getpid()}" in report
    # one seed of hierarchical=false pairs with one of hierarchical=true: no interval, so one line
    assert "1. hierarchical=false (25.00 dB), hierarchical=true (22.00 dB)" in report
    assert "No reference variant" in report and "PSNR - reference" not in report


def test_runs_in_different_precisions_are_said_to_differ(tmp_path):
    # one sweep in float32 throughout; another whose bf16 variant has a float32 run among its seeds
    uniform, mixed = tmp_path / "uniform", tmp_path / "mixed"
    for seed in range(2):
        make_run(uniform, f"{seed}", ["encoding=posenc", f"seed={seed}"])
        make_run(mixed, f"a{seed}", ["trainer=bf16", f"seed={seed}"], precision="bf16-mixed" if seed else "32-true")
        make_run(mixed, f"b{seed}", ["trainer=default", f"seed={seed}"])
    write_report([uniform], uniform)
    report = (uniform / "report.md").read_text()
    assert "Every run trained in 32-true precision." in report and "| precision |" not in report
    write_report([mixed], mixed)
    report = (mixed / "report.md").read_text()
    assert "Runs trained in different precisions (32-true, bf16-mixed)" in report
    assert "Variants whose own runs differ in precision: trainer=bf16." in report
    assert "| trainer=bf16 | 2/2 | 20.00 ± 0.00 | 0.800 ± 0.000 | 32-true (1), bf16-mixed (1) |" in report
    rows = {row["variant"]: row["precision"] for row in read_csv(mixed / "report.csv")}
    assert rows == {"trainer=bf16": "32-true (1), bf16-mixed (1)", "trainer=default": "32-true"}


def test_an_earlier_nerfexps_run_has_its_precision_read_from_its_config():
    assert run_precision({"config": {"trainer": {"precision": "16-mixed"}}}) == "16-mixed"
    assert run_precision({"precision": "bf16-mixed", "config": {"trainer": {"precision": "auto"}}}) == "bf16-mixed"
    assert run_precision({}) == "unrecorded"


def test_plots_are_pngs_of_the_stated_size(sweep):
    write_report([sweep], sweep)
    for name in ("psnr_vs_time.png", "pareto.png", "difference_vs_time.png"):
        image = iio.imread(sweep / name)
        assert image.shape[:2] == (500, 800) and image.std() > 0  # 8 x 5 inches at 100 dpi, not blank


T_975_2 = 4.3027  # Student's t, two-sided 95%, 2 degrees of freedom (a t table)


@pytest.fixture
def ablation(tmp_path):
    """Four ablation rows x seeds 0, 1, 2 on the built-in scene, test PSNR chosen so that, against
    complete (28.0, 28.2, 27.8): no_posenc is +1.0, +1.1, +0.9 (resolved better), fewer_images +0.1, -0.1,
    +0.2 (not resolved), no_view_dependence -3.0, -2.7, -3.3 (resolved worse)."""
    rows = {"complete": (28.0, 28.2, 27.8), "no_posenc": (29.0, 29.3, 28.7), "fewer_images": (28.1, 28.1, 28.0),
            "no_view_dependence": (25.0, 25.5, 24.5)}
    for row, psnrs in rows.items():
        for seed, psnr in enumerate(psnrs):
            make_run(tmp_path, f"{row}_{seed}", [f"ablation={row}", f"seed={seed}"], psnr=psnr,
                     choices={"ablation": row, "data": "procedural"})
    return tmp_path


def test_each_variant_against_the_complete_model_paired_by_seed(ablation):
    write_report([ablation], ablation)
    table = {row["variant"]: row for row in read_csv(ablation / "report.csv")}
    assert table["ablation=complete"]["reference"] == "reference"
    no_pe = table["ablation=no_posenc"]
    half = T_975_2 * 0.1 / math.sqrt(3)  # differences 1.0, 1.1, 0.9: s = 0.1
    assert (no_pe["reference"], no_pe["paired_seeds"], no_pe["verdict"]) == ("ablation=complete", "3", "better")
    assert [float(no_pe[k]) for k in ("psnr_diff", "psnr_diff_low", "psnr_diff_high")] == pytest.approx(
        [1.0, 1.0 - half, 1.0 + half], abs=1e-4)
    assert table["ablation=fewer_images"]["verdict"] == "not resolved with 3 seeds"
    assert table["ablation=no_view_dependence"]["verdict"] == "worse"
    assert float(table["ablation=no_view_dependence"]["ssim_diff"]) == 0.0  # every run's SSIM is 0.8
    report = (ablation / "report.md").read_text()
    assert "| ablation=no_posenc | 3/3 | 29.00 ± 0.30 | 0.800 ± 0.000 | +1.00 [+0.75, +1.25] |" in report
    assert "Reference: `ablation=complete`." in report
    # no_posenc is resolved above fewer_images (0.9, 1.2, 0.7); complete is not resolved from fewer_images
    assert ("1. ablation=no_posenc (29.00 dB)\n2. ablation=fewer_images (28.07 dB), ablation=complete (28.00 dB)\n"
            "3. ablation=no_view_dependence (25.00 dB)") in report


def test_lpips_beside_psnr_and_ssim_where_runs_scored_it_lower_being_better(tmp_path):
    # complete: 0.20, 0.22, 0.18; no_posenc 0.05, 0.06, 0.04 higher (worse); fewer_images from before LPIPS
    lpips = {"complete": (0.20, 0.22, 0.18), "no_posenc": (0.25, 0.28, 0.22), "fewer_images": (None,) * 3}
    psnrs = {"complete": (28.0, 28.2, 27.8), "no_posenc": (29.0, 29.3, 28.7), "fewer_images": (28.1, 28.1, 28.0)}
    for row in lpips:
        for seed in range(3):
            make_run(tmp_path, f"{row}_{seed}", [f"ablation={row}", f"seed={seed}"], psnr=psnrs[row][seed],
                     lpips=lpips[row][seed], choices={"ablation": row, "data": "procedural"})
    write_report([tmp_path], tmp_path)
    table = {row["variant"]: row for row in read_csv(tmp_path / "report.csv")}
    no_pe, complete, fewer = (table[f"ablation={r}"] for r in ("no_posenc", "complete", "fewer_images"))
    assert [float(complete[k]) for k in ("test_lpips_mean", "test_lpips_std")] == pytest.approx([0.20, 0.02])
    half = T_975_2 * 0.01 / math.sqrt(3)  # differences 0.05, 0.06, 0.04: s = 0.01
    assert [float(no_pe[k]) for k in ("lpips_diff", "lpips_diff_low", "lpips_diff_high")] == pytest.approx(
        [0.05, 0.05 - half, 0.05 + half], abs=1e-6)  # the table's t to 5 figures
    assert no_pe["verdict"] == "better"  # the verdict is PSNR's; LPIPS rose: worse, which the table's sign says
    assert all(math.isnan(float(fewer[k])) for k in ("test_lpips_mean", "lpips_diff", "lpips_diff_low"))
    report = (tmp_path / "report.md").read_text()
    assert "| test SSIM | test LPIPS | PSNR - reference (95% CI) | SSIM - reference (95% CI) | LPIPS - reference " \
           "(95% CI; lower is better) | verdict (PSNR) |" in report
    assert "| ablation=no_posenc | 3/3 | 29.00 ± 0.30 | 0.800 ± 0.000 | 0.250 ± 0.030 | +1.00 [+0.75, +1.25] | " \
           "+0.000 [+0.000, +0.000] | +0.050 [+0.025, +0.075] | better |" in report
    assert "| ablation=fewer_images | 3/3 | 28.07 ± 0.06 | 0.800 ± 0.000 | – | +0.07 [-0.31, +0.45] | " \
           "+0.000 [+0.000, +0.000] | – | not resolved with 3 seeds |" in report
    assert "| ablation=complete | 3/3 | 28.00 ± 0.20 | 0.800 ± 0.000 | 0.200 ± 0.020 | reference | reference | " \
           "reference | reference |" in report
    assert "LPIPS is AlexNet's (v0.1" in report and "a paper's LPIPS is VGG's" in report


@pytest.mark.parametrize("recorded", [{}, {"lpips_weights_sha256": "0" * 64}])
def test_lpips_nerfexp_cannot_vouch_for_is_left_out_and_said(tmp_path, recorded):
    # run a_1 scored "LPIPS" without the published weights' digest (an earlier nerfexp's run, or other weights): its
    # number is left out of the table and the comparison, and report.md names the run
    for seed in range(2):
        make_run(tmp_path, f"a_{seed}", ["ablation=a", f"seed={seed}"], lpips=0.2 + seed / 10)
    results_file = tmp_path / "a_1" / "results.json"
    results = json.loads(results_file.read_text())
    del results["lpips_weights_sha256"]
    results_file.write_text(json.dumps({**results, **recorded}))
    write_report([tmp_path], tmp_path)
    (row,) = read_csv(tmp_path / "report.csv")
    assert float(row["test_lpips_mean"]) == pytest.approx(0.2) and math.isnan(float(row["test_lpips_std"]))
    report = (tmp_path / "report.md").read_text()
    assert (f"The LPIPS of 1 run(s) is left out (`{tmp_path / 'a_1'}`): their results.json does not show "
            "torchvision's published AlexNet weights by their SHA-256") in report


def test_lpips_of_own_weights_is_never_tabled_as_lpips(tmp_path):
    for seed in range(2):
        run = make_run(tmp_path, f"own_{seed}", ["ablation=own", f"seed={seed}"])
        results = json.loads((run / "results.json").read_text())
        results.update(test_lpips_custom=0.05, test_lpips_custom_per_view=[0.05], lpips_weights_sha256="1" * 64)
        (run / "results.json").write_text(json.dumps(results))
    write_report([tmp_path], tmp_path)
    assert "LPIPS" not in (tmp_path / "report.md").read_text()
    assert all(math.isnan(float(row["test_lpips_mean"])) for row in read_csv(tmp_path / "report.csv"))


def test_without_lpips_the_report_has_no_lpips_column(ablation):
    write_report([ablation], ablation)
    assert "LPIPS" not in (ablation / "report.md").read_text()
    assert all(math.isnan(float(row["test_lpips_mean"])) and math.isnan(float(row["lpips_diff"]))
               for row in read_csv(ablation / "report.csv"))


def test_the_papers_order_counts_agreements_reversals_and_unresolved_pairs_each_named(ablation):
    write_report([ablation], ablation)
    report = (ablation / "report.md").read_text()
    # the paper: complete 31.01 > fewer images 29.79 > no PE 28.77 > no VD 27.66
    assert "Of the 6 pairs the paper orders: 3 resolved in the paper's order, 2 resolved in the other order, " \
           "1 not resolved by these seeds." in report
    reversed_ = report.split("**Resolved in the other order** (2):")[1].split("**Not resolved**")[0]
    assert "- Complete Model above No Pos. Encoding: -1.00 [-1.25, -0.75] dB" in reversed_
    assert "- Fewer Images above No Pos. Encoding: -0.93" in reversed_
    unresolved = report.split("**Not resolved** (1):")[1]
    assert "- Complete Model above Fewer Images: -0.07 [" in unresolved
    # and no published number beside runs on the built-in scene (tests/report/test_publications.py), nor a word of them
    assert all(math.isnan(float(row["published_psnr"])) for row in read_csv(ablation / "report.csv"))
    assert "Published numbers" not in report
    assert [PAPER_ABLATION[k][1] for k in ("complete", "no_pe_vd_h")] == [31.01, 26.67]


def test_two_ablation_rows_are_one_pair_of_the_papers_order(tmp_path):
    for seed, (complete, no_posenc) in enumerate([(30.0, 28.0), (31.0, 28.5)]):  # by hand: +2.0, +2.5; mean +2.25
        make_run(tmp_path, f"c{seed}", ["ablation=complete", f"seed={seed}"], psnr=complete,
                 choices={"ablation": "complete"})
        make_run(tmp_path, f"n{seed}", ["ablation=no_posenc", f"seed={seed}"], psnr=no_posenc,
                 choices={"ablation": "no_posenc"})
    write_report([tmp_path], tmp_path)
    report = (tmp_path / "report.md").read_text()
    assert "## Against the paper's order (2 ablation rows, 1 pair)" in report
    assert "Of the 1 pair the paper orders: 0 resolved in the paper's order," in report
    assert "- Complete Model above No Pos. Encoding: +2.25 [" in report


SECTIONS = ["## Ranking by mean test PSNR", "## Against the paper's order", "## Per budget",  # report.md's, in order
            "## At equal training time", "## Jobs that did not finish", "## How these numbers were computed"]


@pytest.mark.parametrize("other_host", [False, True])
def test_the_table_and_its_verdicts_come_first_each_caveat_said_once_below_it_and_the_method_last(ablation,
                                                                                                   other_host):
    # the ablation sweep with one run beside other work, one in bf16, and (other_host) a row on another machine
    for name, change in (("no_posenc_1", {"other_load": 1.5, "cpu_time_s": 50.0, "cpus": 2}),
                         ("fewer_images_2", {"precision": "bf16-mixed"}),
                         *((("no_view_dependence_0", {"machine": {"host": "gpu-b", "device": "GPU"}}),)
                           if other_host else ())):
        results = json.loads((ablation / name / "results.json").read_text())
        (ablation / name / "results.json").write_text(json.dumps({**results, **change}))
    write_report([ablation], ablation)
    report = (ablation / "report.md").read_text()
    head, *sections = report.split("\n## ")
    headings = [f"## {section.splitlines()[0]}" for section in sections]
    assert len(headings) == len(SECTIONS) and all(map(str.startswith, headings, SECTIONS))  # in order, method last
    # first the title, what was compared against what, the table with its verdicts; then what it needs said
    lines = head.splitlines()
    assert lines[:3] == ["# nerfexp report", "", f"Runs: 12 (12 finished) from `{ablation}`. Reference: "
                                                 "`ablation=complete`."]
    assert lines[4].startswith("| variant |") and "| verdict (PSNR) |" in lines[4] and lines[6].startswith("| ")
    notes = head.split("|\n\n", 1)[1]  # below the table
    caveats = {"different precisions": "Runs trained in different precisions",
               "a shared machine": f"`{ablation / 'no_posenc_1'}` (1.50)",
               **({"two machines": "The runs come from 2 machines"} if other_host else {})}
    for words in caveats.values():
        assert report.count(words) == 1 and words in notes  # once, below the table
    assert report.count("come from 2 machines") == int(other_host) and "Runs come from different machines" not in report
    # the method once, at the end: how the differences, the ranking and the times were computed
    method = sections[-1]
    for words in ("Student's t, n - 1 degrees of freedom", "Ranking: variants by mean test PSNR",
                  "Times are training wall-clock seconds", "Plots: `psnr_vs_time.png`"):
        assert report.count(words) == 1 and words in method
    equal = next(section for section in sections if section.startswith("At equal training time"))
    assert ("**At " in equal) is not other_host  # ranked by time only where the times may be compared


def test_over_scenes_a_difference_counts_pairs_of_a_seed_on_a_scene_not_seeds(tmp_path):
    # 2 seeds x 2 scenes: b - a is +1, -1, +1, -1 (by hand: mean 0, not resolved) over 4 pairs of 2 seeds; c has one run
    for i, (scene, seed) in enumerate([(s, seed) for s in ("s1", "s2") for seed in (0, 1)]):
        over = [f"data.scene={scene}", f"seed={seed}"]
        make_run(tmp_path, f"a{i}", ["model=a", *over], psnr=20.0)
        make_run(tmp_path, f"b{i}", ["model=b", *over], psnr=20.0 + (1 if i % 2 == 0 else -1))
    make_run(tmp_path, "c0", ["model=c", "data.scene=s1", "seed=0"], psnr=21.0)
    write_report([tmp_path], tmp_path, over=("seed", "data.scene"), reference="model=a")
    table = (tmp_path / "report.md").read_text().split("\n## ")[0].splitlines()  # the table, before any section
    (b,) = [line for line in table if line.startswith("| model=b |")]
    (c,) = [line for line in table if line.startswith("| model=c |")]
    assert "| +0.00 [" in b and "| not resolved with 4 pairs |" in b and "seeds" not in b
    assert "| 1 pair: no interval |" in c and "| not resolved with 1 pair |" in c


def test_a_named_reference_and_a_variant_with_one_seed(sweep):
    write_report([sweep], sweep, reference="hierarchical=true")
    report = (sweep / "report.md").read_text()
    # hierarchical=false finished only seed 0: one pair, no interval
    assert "| hierarchical=false | 1/3 | 25.00 | 0.950 | 1 seed: no interval | 1 seed: no interval | " \
           "not resolved with 1 seed |" in report
    assert "| encoding=none | 0/1 | – | – | – | – | – |" in report  # nothing finished: nothing to compare
    # true, false and null in any case, as Hydra reads them (a sweep file's true,false reaches the runs as True, False)
    write_report([sweep], sweep, reference="hierarchical=True")
    assert (sweep / "report.md").read_text() == report
    with pytest.raises(SystemExit, match="--reference 'hierarchical=maybe': no such variant; the variants are "):
        write_report([sweep], sweep, reference="hierarchical=maybe")


def test_mean_curves_use_the_steps_every_run_reached():
    runs = [Run(Path(str(i)), "finished", [], curve=curve) for i, curve in enumerate([
        [(10, 5.0, 20.0), (20, 10.0, 24.0)], [(10, 7.0, 22.0), (20, 12.0, 25.0), (30, 17.0, 26.0)]])]
    assert mean_curve(runs) == [(6.0, 21.0, 20.0, 22.0), (11.0, 24.5, 24.0, 25.0)]
    assert mean_curve([]) == []


def test_averaging_over_scenes_and_machines_are_named(tmp_path):
    for i, (root, psnr, host) in enumerate([("/d/lego", 30.0, "gpu-a"), ("/d/ship", 26.0, "gpu-b")]):
        make_run(tmp_path, str(i), ["ablation=complete", f"data.root={root}", "seed=0"], psnr=psnr, host=host)
    variants = group_variants(find_runs([tmp_path]), over=("seed", "data.root"))
    assert [(v.label, v.mean("test_psnr")) for v in variants] == [("ablation=complete", 28.0)]
    assert len(group_variants(find_runs([tmp_path]))) == 2  # by default each scene is its own variant
    write_report([tmp_path], tmp_path)
    assert "not comparable with each other" in (tmp_path / "report.md").read_text()


def test_the_command_line(tmp_path, sweep):
    out = tmp_path / "out"
    main([str(sweep), "--out", str(out)])
    assert {p.name for p in out.iterdir()} == {"report.md", "report.csv", "report_budgets.csv", "psnr_vs_time.png",
                                              "pareto.png", "difference_vs_time.png", "report.html", "report_images",
                                              *manifest.BOOKKEEPING}
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(SystemExit, match="no runs"):
        main([str(empty)])
    with pytest.raises(SystemExit, match="is not a directory"):
        main([str(tmp_path / "missing")])


def test_jobs_a_stopped_sweep_never_started_are_counted(tmp_path):
    # multirun.yaml plans hierarchical x seed = 2 x 3 = 6 jobs (as Hydra's basic sweeper writes it);
    # four job directories exist.
    (tmp_path / "multirun.yaml").write_text(
        "hydra:\n  sweeper:\n    _target_: hydra._internal.core_plugins.basic_sweeper.BasicSweeper\n"
        "    params:\n      hierarchical: true,false\n      seed: 0,1,2\n  overrides:\n    task: [scale.steps=10]\n")
    for i in range(4):
        make_run(tmp_path, str(i), [f"hierarchical={'true' if i < 3 else 'false'}", f"seed={i % 3}", "scale.steps=10"])
    write_report([tmp_path], tmp_path)
    assert f"`{tmp_path}` plans 6 jobs, 4 started: the rest never started" in (tmp_path / "report.md").read_text()


BASIC_SWEEPER = "hydra:\n  sweeper:\n    _target_: hydra._internal.core_plugins.basic_sweeper.BasicSweeper\n"


@pytest.mark.parametrize(("params", "jobs"), [
    ("      seed: range(0,1000000000)\n", 1_000_000_000),  # counted, never listed
    ("      seed: range(0,1,0.25)\n      encoding: none,posenc\n", 8),
    ("      seed: choice(0,1)\n      hierarchical: ${oc.env:NERFEXP_TEST_SECRET}\n", 2),  # text, never resolved
    ("      seed: sort(range(0,1000000000))\n", None),  # sort lists what it sorts: not counted
    ("      seed: range(0,3,0)\n", None),
])
def test_a_sweeps_planned_jobs_are_counted_without_expanding_or_resolving(tmp_path, params, jobs, monkeypatch):
    monkeypatch.setenv("NERFEXP_TEST_SECRET", "0,1,2")
    (tmp_path / "multirun.yaml").write_text(f"{BASIC_SWEEPER}    params:\n{params}  overrides:\n    task: []\n")
    assert planned_jobs(tmp_path) == jobs


def test_a_key_the_command_line_sweeps_replaces_the_sweepers_params_of_that_key_in_the_count(tmp_path):
    # nerfexp +sweeps=budgets ablation=complete,no_view_dependence,no_hierarchical: sweeps/budgets.yaml's params
    # sweep 4 ablation rows x 3 seeds; the command line's 3 rows replace its 4, and Hydra launched 9 jobs
    (tmp_path / "multirun.yaml").write_text(
        f"{BASIC_SWEEPER}    params:\n      ablation: complete,no_posenc,no_view_dependence,no_hierarchical\n"
        "      seed: 0,1,2\n  overrides:\n    task: [+sweeps=budgets, 'ablation=complete,no_view_dependence,"
        "no_hierarchical', data=blender]\n")
    assert planned_jobs(tmp_path) == 9


LAUGHS = "a: &a [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n" + "".join(
    f"{b}: &{b} [{', '.join(['*' + a] * 9)}]\n" for a, b in zip("abcdefgh", "bcdefghi"))


@pytest.mark.parametrize(("content", "reason"), [
    (b"{}", "not a sweep's multirun.yaml (it has no hydra.sweeper)"),
    (b"hydra: [unclosed\n", "not YAML ("),
    (bytes(range(256)), "not UTF-8 text"),
    (LAUGHS.encode(), "a YAML anchor or alias, which nerfexp does not read"),
    ((BASIC_SWEEPER + "    params: [1]\n").encode(), "its sweeper's params or task overrides are not a mapping"),
])
def test_a_damaged_multirun_yaml_costs_the_report_its_planned_count_only(tmp_path, content, reason):
    (tmp_path / "multirun.yaml").write_bytes(content)
    make_run(tmp_path, "0", ["seed=0"])
    with pytest.raises(UnreadableFile, match=re.escape(reason)):
        planned_jobs(tmp_path)
    write_report([tmp_path], tmp_path)
    report = (tmp_path / "report.md").read_text()
    assert f"- `{tmp_path / 'multirun.yaml'}` not read (" in report and reason in report
    assert "how many jobs the sweep planned is unknown" in report and "Runs: 1 (1 finished)" in report


def test_the_order_of_overrides_does_not_split_a_variant(tmp_path):
    make_run(tmp_path, "0", ["ablation=complete", "seed=0", "+sweeps=cpu_ablation"], psnr=20.0)
    make_run(tmp_path, "1", ["+sweeps=cpu_ablation", "seed=1", "ablation=complete"], psnr=22.0)
    make_run(tmp_path, "2", ["ablation=no_posenc", "seed=0", "+sweeps=cpu_ablation"], psnr=18.0)
    variants = group_variants(find_runs([tmp_path]))
    assert [(v.label, v.mean("test_psnr")) for v in variants] == [("ablation=complete", 21.0),
                                                                  ("ablation=no_posenc", 18.0)]


def test_a_running_job_whose_pid_now_belongs_to_another_process_was_killed(tmp_path):
    # the status names this test's own pid, but a process started at another time: the system reused
    # the pid of the job's process, which is gone
    run = make_run(tmp_path, "0", ["seed=0"], state="running", pid=os.getpid())
    status = json.loads((run / "status.json").read_text())
    (run / "status.json").write_text(json.dumps({**status, "process_start": process_start(os.getpid()) + 1}))
    (job,) = find_runs([tmp_path])
    assert job.state == "killed" and f"process {os.getpid()} is gone" in job.detail
    (run / "status.json").write_text(json.dumps({**status, "process_start": process_start(os.getpid())}))
    assert find_runs([tmp_path])[0].state == "running"


def test_damaged_runs_are_listed_with_the_file_and_the_reason_and_the_rest_is_reported(sweep):
    (sweep / "0" / "results.json").write_text('{"test_psnr": 20.0, "test_ss')  # truncated
    metrics = (sweep / "1" / "metrics.jsonl").read_text().splitlines()
    (sweep / "1" / "metrics.jsonl").write_text("\n".join([metrics[0][:15], *metrics[1:]]) + "\n")  # a torn line
    (sweep / "3" / "status.json").write_text("")  # empty: the overrides are read from results.json
    write_report([sweep], sweep)
    report = (sweep / "report.md").read_text()
    assert "Runs: 7 (1 finished, 1 failed, 1 killed, 1 running, 3 damaged)" in report
    assert f"- `{sweep / '0'}` (hierarchical=true, seed=0): damaged: results.json: not JSON (" in report
    assert f"- `{sweep / '1'}` (hierarchical=true, seed=1): damaged: metrics.jsonl: line 1 is not JSON (" in report
    assert f"- `{sweep / '3'}` (hierarchical=false, seed=0): damaged: status.json: not JSON (" in report
    rows = {row["variant"]: row for row in read_csv(sweep / "report.csv")}
    assert float(rows["hierarchical=true"]["test_psnr_mean"]) == 24.0  # seed 2 alone is counted
    # damaged jobs count against their variant; one whose jobs are all unusable stays in the table
    assert {name: (row["finished"], row["runs"]) for name, row in rows.items()} == {
        "hierarchical=true": ("1", "3"), "hierarchical=false": ("0", "3"), "encoding=none": ("0", "1")}
    # the same through the command line: exit status 0 and the report written
    (sweep / "report.md").unlink()
    result = subprocess.run([str(Path(sys.executable).with_name("nerfexp-report")), str(sweep)],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0 and "Traceback" not in result.stderr, result.stderr[-2000:]
    report = (sweep / "report.md").read_text()
    assert "3 damaged" in report
    assert "| hierarchical=true | 1/3 |" in report and "| hierarchical=false | 0/3 |" in report


def test_a_damaged_job_whose_overrides_cannot_be_read_joins_no_variant(sweep):
    (sweep / "3" / "status.json").write_text("[")
    (sweep / "3" / "results.json").write_text("")
    runs = find_runs([sweep])
    assert [run.overrides for run in runs if run.state == "damaged"] == [None]
    write_report([sweep], sweep)
    report = (sweep / "report.md").read_text()
    assert f"- `{sweep / '3'}` (overrides unreadable): damaged: status.json: not JSON (" in report
    rows = {row["variant"]: row for row in read_csv(sweep / "report.csv")}
    assert set(rows) == {"hierarchical=true", "hierarchical=false", "encoding=none"}
    assert (rows["hierarchical=false"]["finished"], rows["hierarchical=false"]["runs"]) == ("0", "2")


def cut_last_line(run: Path) -> None:
    """Cut the last line of a run's ``metrics.jsonl`` short, as a full disk or a kill mid-write leaves it."""
    text = (run / "metrics.jsonl").read_text()
    (run / "metrics.jsonl").write_text(text[:-10])


def test_a_cut_last_metrics_line_is_damage_in_a_run_that_ended_not_in_one_that_runs(sweep):
    for name in ("0", "4", "6"):  # finished, failed, running (this test's own process)
        cut_last_line(sweep / name)
    result = subprocess.run([str(Path(sys.executable).with_name("nerfexp-report")), str(sweep)],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0 and "Traceback" not in result.stderr, result.stderr[-2000:]
    report = (sweep / "report.md").read_text()
    assert "Runs: 7 (3 finished, 1 killed, 1 running, 2 damaged)" in report
    assert (f"- `{sweep / '0'}` (hierarchical=true, seed=0): damaged: metrics.jsonl: line 3, the last, is cut "
            "(no newline, and the run has ended)") in report
    assert (f"- `{sweep / '4'}` (hierarchical=false, seed=1): damaged: metrics.jsonl: line 2, the last, is cut "
            "(no newline, and the run has ended) (the job failed: NonFiniteError: step 7:") in report
    running = next(run for run in find_runs([sweep]) if run.path.name == "6")
    assert running.state == "running" and running.curve == [(10, 50.0, 15.0)]  # the line being written left out
    assert "| hierarchical=true | 2/3 | 23.00 ± 1.41 |" in report


def test_a_report_writes_over_its_own_files_and_beside_a_users(tiny_run, tmp_path):
    out = tmp_path / "out"
    (out / "0").mkdir(parents=True)
    (out / "0" / "status.json").write_text("{}")
    (out / "notes.txt").write_text("mine")  # of a name the report does not write: left beside it
    main([str(tiny_run), "--out", str(out)])
    pages = ["report.md", "report.csv", "report_budgets.csv", "report.html", "psnr_vs_time.png", "pareto.png",
             "difference_vs_time.png"]
    images = manifest.folder_files(out, "report_images")
    assert "report_images/view0/truth.png" in images and manifest.unproven(out, [*pages, *images]) == []
    (out / images[0]).unlink()  # gone since: nothing to lose
    main([str(tiny_run), "--out", str(out), "--views", "1"])  # its own report: replaced, the pictures as a whole
    images = manifest.folder_files(out, "report_images")
    assert "report_images/view1/truth.png" in images and all(image.startswith("report_images/view1/")
                                                             for image in images)
    assert manifest.read_records(out).keys() == {*pages, *images}  # the records of the pictures gone, forgotten
    assert (out / "notes.txt").read_text() == "mine" and (out / "0" / "status.json").read_text() == "{}"


def test_a_report_refuses_to_write_over_a_users_files_of_its_names_and_writes_nothing(sweep):
    main([str(sweep)])  # the sweep's own report, then the user's files in its names
    (sweep / "report.md").write_text("DO NOT LOSE")
    (sweep / "report.csv").write_text("mine,too\n")
    (sweep / "report_images" / "view0").mkdir(parents=True)
    (sweep / "report_images" / "view0" / "holiday.png").write_bytes(b"\x89PNG a holiday")
    before = digests(sweep)
    with pytest.raises(SystemExit) as exit:
        main([str(sweep)])
    assert exit.value.code == (
        f"nerfexp-report: error: {sweep / 'report.md'}, {sweep / 'report.csv'}, "
        f"{sweep / 'report_images/view0/holiday.png'} are not files nerfexp-report wrote (they are not in "
        f"{sweep / manifest.MANIFEST}, or changed since): move them, or choose another folder for the report "
        "(--out DIR)")
    assert digests(sweep) == before and not list(sweep.glob(".report*"))
    for name in ("report.md", "report.csv", "report_images"):  # moved: the report is written
        (sweep / name).rename(sweep.parent / name)
    main([str(sweep)])
    assert (sweep.parent / "report.md").read_text() == "DO NOT LOSE" and (sweep / "report.md").is_file()


@pytest.mark.parametrize("label", ["=HYPERLINK(\"http://x\",\"y\")", "+1+2", "-2+3", "@SUM(A1:A9)", "\t=1+2",
                                   "\r=1+2"])
def test_report_csv_text_cells_that_a_spreadsheet_would_read_as_a_formula_are_prefixed(tmp_path, label):
    # OWASP's CSV injection guidance: a text cell starting with =, +, -, @, tab or carriage return gets a
    # leading ' (read as "this is text"); numbers, negative ones included, are written as numbers
    make_run(tmp_path, "0", [label, "seed=0"], psnr=20.0)
    make_run(tmp_path, "1", ["ablation=complete", "seed=0"], psnr=22.0)
    write_report([tmp_path], tmp_path, reference=label)
    with open(tmp_path / "report.csv", newline="") as file:  # a carriage return inside a quoted cell kept
        rows = {row["variant"]: row for row in csv.DictReader(file)}
    assert set(rows) == {"'" + label, "ablation=complete"}
    assert rows["ablation=complete"]["reference"] == "'" + label  # every text cell, not only the label's
    assert rows["ablation=complete"]["psnr_diff"] == "2.0" and rows["'" + label]["psnr_diff"] == "nan"
    ours = rows["'" + label]
    assert ours["test_psnr_mean"] == "20.0" and ours["runs"] == "1"
    make_run(tmp_path, "2", ["ablation=no_posenc", "seed=0"], psnr=19.5)
    write_report([tmp_path], tmp_path, reference="ablation=complete")
    rows = {row["variant"]: row for row in read_csv(tmp_path / "report.csv")}
    assert rows["ablation=no_posenc"]["psnr_diff"] == "-2.5"  # a negative number stays a number


def labelled(run: Path, tags: list, notes: str | None = None) -> Path:
    """``run`` (``make_run``'s) with the labels nerfexp records: in status.json, and in results.json where it has
    one."""
    for name in ("status.json", "results.json"):
        if (run / name).exists():
            record = json.loads((run / name).read_text())
            (run / name).write_text(json.dumps({**record, "tags": tags, "notes": notes}))
    return run


def test_runs_that_differ_only_in_tags_and_notes_are_one_variant_that_shows_them(tmp_path):
    labelled(make_run(tmp_path, "0", ["hierarchical=true", "seed=0", "tags=[baseline]", "notes=first try"],
                      psnr=20.0), ["baseline"], "first try")
    labelled(make_run(tmp_path, "1", ["seed=1", "tags=[baseline,x|y]", "hierarchical=true"], psnr=22.0),
             ["baseline", "x|y"])
    labelled(make_run(tmp_path, "2", ["hierarchical=true", "seed=2"], state="failed", error="ValueError: x"),
             ["late"])  # from a sweep file: no override; a job that failed has its tags in its status
    make_run(tmp_path, "3", ["hierarchical=false", "seed=0"], psnr=25.0)
    variants = group_variants(find_runs([tmp_path]))
    assert [(v.label, len(v.runs), v.mean("test_psnr")) for v in variants] == [("hierarchical=false", 1, 25.0),
                                                                            ("hierarchical=true", 3, 21.0)]
    assert (variants[1].tags, variants[1].notes) == (["baseline", "x|y", "late"], ["first try"])
    assert (variants[0].tags, variants[0].notes) == ([], [])  # an earlier nerfexp's run: no labels
    write_report([tmp_path], tmp_path)
    rows = {row["variant"]: row for row in read_csv(tmp_path / "report.csv")}
    assert json.loads(rows["hierarchical=true"]["tags"]) == ["baseline", "x|y", "late"]
    assert json.loads(rows["hierarchical=true"]["notes"]) == ["first try"]
    assert (rows["hierarchical=false"]["tags"], rows["hierarchical=false"]["notes"]) == ("[]", "[]")
    report = (tmp_path / "report.md").read_text()
    assert "| variant | tags | runs |" in report
    assert "| hierarchical=true | baseline, x\\|y, late | 2/3 | 21.00 ± 1.41 |" in report  # | kept in its cell
    assert "| hierarchical=false |  | 1/1 |" in report and "- hierarchical=true: first try" in report
    html = (tmp_path / "report.html").read_text()
    assert "<td>baseline, x|y, late</td>" in html and "<li>hierarchical=true: first try</li>" in html


def test_runs_that_differ_only_in_their_test_budgets_are_one_variant(tmp_path):
    # test_budgets says when the test views are scored, not what trains: runs scored at other budgets pair by seed
    make_run(tmp_path, "0", ["hierarchical=true", "seed=0", "test_budgets=[0.5]"], psnr=20.0)
    make_run(tmp_path, "1", ["hierarchical=true", "seed=1"], psnr=22.0)
    make_run(tmp_path, "2", ["hierarchical=false", "seed=0", "test_budgets=[]"], psnr=25.0)
    variants = group_variants(find_runs([tmp_path]))
    assert [(v.label, len(v.runs)) for v in variants] == [("hierarchical=false", 1), ("hierarchical=true", 2)]


def test_a_run_whose_labels_are_not_as_nerfexp_writes_them_is_damaged(tmp_path):
    labelled(make_run(tmp_path, "0", ["seed=0"]), "baseline")  # a text, not a list
    (run,) = find_runs([tmp_path])
    assert run.state == "damaged" and run.detail == "results.json: tags or notes that are not as nerfexp writes them"
