"""Test scores at several budgets of one run (``test_budgets``, nerfexp.training.budgets): each budget's scores are
those ``nerfexp-eval`` gives the checkpoint of its step, scoring them changes nothing that is trained, and
``results.json`` lists them in step order with the final test's last, kept across a resume. Their cost is measured
before it is paid: under ``auto`` (the default) budgets that would cost more than a quarter of the training are
not scored, with a line; a list given is scored as set."""

import json
import math
import re
import time
import types
from collections.abc import Callable
from pathlib import Path

import pytest
import torch

from nerfexp.training.budgets import (
    AUTO,
    COST_SHARE,
    DEFAULT_FRACTIONS,
    affordable_budgets,
    budget_entry,
    budget_steps,
    budget_text,
    score_test_views,
    scoring_seconds,
    training_estimate_s,
)
from nerfexp.training.module import NeRFModule
from nerfexp.training.recorders import RunRecorder
from tests.helpers import TINY, one_error_line, read_json, run_nerfexp, tiny_config

# a tiny run's checkpoints at every validation (steps 30 and 60) kept under their own names: the budget of 1/2
# has one to be scored against
EVERY_CHECKPOINT = "callbacks.checkpoint.save_top_k=-1"
MID = "epoch=0-step=30.ckpt"


@pytest.mark.parametrize(("fractions", "max_steps", "expected"), [
    ([0.25, 0.5], 4000, [1000, 2000]),
    ([0.25, 0.5], 60, [15, 30]),
    ([0.1, 0.5], 5, [1, 2]),  # round(0.5) and round(2.5) are 0 and 2 (half to even); at least step 1
    ([0.3], 10, [3]),  # 0.3 x 10 = 3.0000000000000004
    ([0.001, 0.002], 100, [1]),  # at least one step, the same step once
    ([0.5, 0.9, 0.99], 10, [5, 9]),  # 9.9 rounds to 10: the end, which the final test scores
    ([0.5], 1, []),  # a run of one step: only its end
    ([], 100, []),
])
def test_budget_steps_are_rounded_at_least_one_once_each_and_before_the_end(fractions, max_steps, expected):
    assert budget_steps(fractions, max_steps) == expected


def test_a_budget_is_said_as_a_simple_fraction_where_it_is_one():
    assert [budget_text(f) for f in (0.25, 0.5, 0.75, 0.1, 0.333)] == ["1/4", "1/2", "3/4", "1/10", "0.333"]


def test_a_budget_records_the_means_of_its_scores_and_never_a_nan():
    scores = {1: {"psnr": 30.0, "ssim": 0.75, "lpips": math.nan, "contrast": 0.2},
              0: {"psnr": 20.0, "ssim": 0.25, "lpips": 0.5, "contrast": 0.1}}
    assert budget_entry(10, 2.5, 1e6, scores, 0.5) == {
        "step": 10, "train_time_s": 2.5, "evaluations": 1e6, "test_psnr": 25.0, "test_ssim": 0.5, "score_s": 0.5}
    scores[1]["lpips"] = 0.25
    assert budget_entry(10, 2.5, 1e6, scores, 0.5)["test_lpips"] == 0.375
    entries = [{"score_s": 0.25}, {"score_s": 0.5}, {"score_s": 8.0}]  # the last is the final test's
    assert scoring_seconds(entries) == 0.75 and scoring_seconds(entries[-1:]) == 0.0


def test_a_checkpoint_of_an_earlier_nerfexp_holds_no_budget(tmp_path):
    recorder = RunRecorder(str(tmp_path), {}, test_budgets=[0.5])
    recorder.budgets = [{"step": 3}]
    recorder.load_state_dict({"elapsed_s": 1.0})  # what an earlier nerfexp's checkpoint recorded
    assert recorder.budgets == []
    saved = {**recorder.state_dict(), "test_budgets": [{"step": 5, "test_psnr": 20.0}]}
    recorder.load_state_dict(saved)
    assert recorder.budgets == [{"step": 5, "test_psnr": 20.0}]


class Scored(torch.nn.Module):
    """A module that scores a view as ``NeRFModule.test_step`` returns it, drawing random numbers as it does and
    recording the modes it scored in and whether gradients were off."""

    def __init__(self):
        super().__init__()
        self.head, self.frozen = torch.nn.Linear(1, 1), torch.nn.Linear(1, 1).eval()  # one left in evaluation mode
        self.seen: list[tuple] = []

    @property
    def device(self) -> torch.device:
        return torch.device("cpu")

    def test_step(self, batch: dict, batch_idx: int) -> dict:
        torch.rand(())  # from the global stream, as a render's noise would draw
        self.seen.append((self.training, self.head.training, torch.is_inference_mode_enabled(), batch_idx))
        return {"index": int(batch["index"]), "psnr": 20.0 + batch_idx, "ssim": 0.5, "contrast": 0.1}


def test_scoring_the_test_views_leaves_the_random_streams_and_the_modes_as_they_were():
    from lightning.pytorch.plugins.precision import Precision
    views = [{"index": torch.tensor(i)} for i in (4, 7)]
    loader = torch.utils.data.DataLoader(views, batch_size=None, shuffle=False)  # its iterator draws a seed
    trainer = types.SimpleNamespace(precision_plugin=Precision(), global_step=3,
                                    strategy=types.SimpleNamespace(batch_to_device=lambda batch: batch),
                                    datamodule=types.SimpleNamespace(test_dataloader=lambda: loader))
    module = Scored().train()
    module.frozen.eval()
    before = torch.random.get_rng_state()
    scores = score_test_views(trainer, module)
    assert torch.equal(torch.random.get_rng_state(), before)
    assert sorted(scores) == [4, 7] and scores[7]["psnr"] == 21.0 and math.isnan(scores[7]["lpips"])
    assert module.seen == [(False, False, True, 0), (False, False, True, 1)]  # evaluation and inference mode
    assert module.training and module.head.training and not module.frozen.training  # each mode as it was


def test_scoring_stops_after_the_view_where_it_is_told_to_and_leaves_everything_as_it_was():
    # test_budgets=auto asks after the first view whether the budget is worth its cost (RunRecorder._affordable)
    from lightning.pytorch.plugins.precision import Precision
    views = [{"index": torch.tensor(i)} for i in (4, 7, 9)]
    loader = torch.utils.data.DataLoader(views, batch_size=None, shuffle=False)
    trainer = types.SimpleNamespace(precision_plugin=Precision(), global_step=3,
                                    strategy=types.SimpleNamespace(batch_to_device=lambda batch: batch),
                                    datamodule=types.SimpleNamespace(test_dataloader=lambda: loader))
    module, asked = Scored().train(), []
    before = torch.random.get_rng_state()
    scores = score_test_views(trainer, module, lambda done, seconds, total: asked.append((done, total)) or done < 2)
    assert sorted(scores) == [4, 7] and asked == [(1, 3), (2, 3)]  # the third view never scored
    assert torch.equal(torch.random.get_rng_state(), before) and module.training


def train(run_dir: Path, *overrides: str, tiny: list[str]) -> dict:
    result = run_nerfexp(*tiny, *overrides, f"hydra.run.dir={run_dir}", cwd=run_dir.parent)
    assert result.returncode == 0, result.stderr[-3000:]
    return read_json(run_dir / "results.json")


@pytest.fixture(scope="module")
def budget_runs(tmp_path_factory) -> dict[str, Path]:
    """The TINY run (60 steps) trained twice: scored at budgets of 1/4 and 1/2 (steps 15 and 30) with every
    checkpoint kept, and with no budget."""
    root = tmp_path_factory.mktemp("budgets")
    runs = {"budgets": root / "budgets", "none": root / "none"}
    train(runs["budgets"], "test_budgets=[0.25,0.5]", EVERY_CHECKPOINT, tiny=TINY)
    train(runs["none"], "test_budgets=[]", tiny=TINY)
    return runs


def test_a_budgets_scores_are_those_of_an_evaluation_of_its_checkpoint(budget_runs, tmp_path):
    run_dir = budget_runs["budgets"]
    result = run_nerfexp(str(run_dir / "checkpoints" / MID), cwd=tmp_path, script="nerfexp-eval")
    assert result.returncode == 0, result.stderr[-3000:]
    evaluated = read_json(run_dir / "eval.json")
    (budget,) = [entry for entry in read_json(run_dir / "results.json")["test_budgets"] if entry["step"] == 30]
    assert evaluated["step"] == 30
    # the same weights, views, chunks and precision as the final test: the same numbers, to float precision
    assert budget["test_psnr"] == pytest.approx(evaluated["test_psnr"], rel=1e-12)
    assert budget["test_ssim"] == pytest.approx(evaluated["test_ssim"], rel=1e-12)


def test_scoring_budgets_changes_nothing_that_is_trained(budget_runs):
    with_budgets, without = (read_json(budget_runs[name] / "results.json") for name in ("budgets", "none"))
    for key in ("test_psnr", "test_ssim", "val_psnr", "test_psnr_per_view", "test_ssim_per_view", "steps"):
        assert with_budgets[key] == without[key], key
    weights = [torch.load(budget_runs[name] / "checkpoints" / "last.ckpt", weights_only=True)["state_dict"]
               for name in ("budgets", "none")]
    assert weights[0].keys() == weights[1].keys()
    assert all(torch.equal(weights[0][key], weights[1][key]) for key in weights[1])
    # the run without budgets has only the end
    assert [entry["step"] for entry in without["test_budgets"]] == [60] and without["budget_scoring_s"] == 0.0


def test_the_budgets_are_recorded_in_step_order_the_end_last_and_their_cost_apart(budget_runs):
    run_dir = budget_runs["budgets"]
    results = read_json(run_dir / "results.json")
    budgets = results["test_budgets"]
    assert [entry["step"] for entry in budgets] == [15, 30, 60]
    end = budgets[-1]
    assert (end["test_psnr"], end["test_ssim"], end["step"], end["train_time_s"]) == (
        results["test_psnr"], results["test_ssim"], results["steps"], results["train_time_s"])
    assert "test_lpips" not in end and "test_lpips_custom" not in end  # no AlexNet weights offline: not scored
    times = [entry["train_time_s"] for entry in budgets]
    assert all(0 < a <= b for a, b in zip(times, times[1:]))
    assert all(entry["score_s"] > 0 for entry in budgets)
    assert results["budget_scoring_s"] == math.fsum(entry["score_s"] for entry in budgets[:2])
    # evaluations: 48 per ray (16 coarse + 16 + 16 fine) x 256 rays a step x the steps
    assert [entry["evaluations"] for entry in budgets] == [48.0 * 256 * step for step in (15, 30, 60)]
    tests = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    tests = [line for line in tests if line["split"] == "test"]
    assert [line["step"] for line in tests] == [15, 30, 60]
    assert [(line["psnr"], line["ssim"], line["wall_time_s"]) for line in tests] == [
        (entry["test_psnr"], entry["test_ssim"], entry["train_time_s"]) for entry in budgets]
    renders = sorted(path.name for path in (run_dir / "test").glob("r_*.png"))
    assert renders == ["r_0.png", "r_0_depth.png", "r_0_error.png", "r_0_target.png",
                       "r_1.png", "r_1_depth.png", "r_1_error.png", "r_1_target.png"]  # the final test's alone


def test_a_resume_at_a_budget_its_checkpoint_lacks_scores_it_before_going_on(budget_runs, tmp_path):
    # Lightning saves checkpoints after the other callbacks' hooks of a step, so a budget's checkpoint holds it; one
    # saved before the budget was scored (another order of the callbacks) is resumed by scoring it first
    checkpoint = torch.load(budget_runs["budgets"] / "checkpoints" / MID, weights_only=True)
    (key,) = [key for key in checkpoint["callbacks"] if key.startswith("RunRecorder")]
    assert [entry["step"] for entry in checkpoint["callbacks"][key]["test_budgets"]] == [15, 30]
    checkpoint["callbacks"][key]["test_budgets"] = checkpoint["callbacks"][key]["test_budgets"][:1]
    torch.save(checkpoint, tmp_path / "before_scoring.ckpt")
    run_dir = tmp_path / "resumed"
    results = train(run_dir, "test_budgets=[0.25,0.5]", f"resume={tmp_path / 'before_scoring.ckpt'}", tiny=TINY)
    original = read_json(budget_runs["budgets"] / "results.json")
    assert [entry["step"] for entry in results["test_budgets"]] == [15, 30, 60]
    for again, first in zip(results["test_budgets"], original["test_budgets"]):  # the same weights at each step
        assert (again["test_psnr"], again["test_ssim"]) == (first["test_psnr"], first["test_ssim"])
    assert results["test_budgets"][0] == original["test_budgets"][0]  # the checkpoint's own, as it recorded it
    tests = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert [line["step"] for line in tests if line["split"] == "test"] == [30, 60]


def test_a_finished_run_trained_further_keeps_each_budget_once(tmp_path):
    # 30 steps scored at 1/2 (step 15) and at their end, then trained to 60 steps, whose 1/2 is step 30: the
    # checkpoint holds the budget of step 15 and not the end, which is scored again, as a budget, before step 31
    run_dir = tmp_path / "run"
    first = train(run_dir, "scale.steps=30", "test_budgets=[0.5]", tiny=TINY)
    assert [entry["step"] for entry in first["test_budgets"]] == [15, 30]
    further = train(run_dir, "scale.steps=60", "test_budgets=[0.5]",
                    f"resume={run_dir / 'checkpoints' / 'last.ckpt'}", tiny=TINY)
    budgets = further["test_budgets"]
    assert [entry["step"] for entry in budgets] == [15, 30, 60]
    assert budgets[0] == first["test_budgets"][0]
    assert (budgets[1]["test_psnr"], budgets[1]["test_ssim"]) == (first["test_psnr"], first["test_ssim"])
    # the clock of its step: the first run's, and what the resumed run counted before its first step
    assert first["train_time_s"] <= budgets[1]["train_time_s"] < budgets[2]["train_time_s"] == further["train_time_s"]
    assert further["budget_scoring_s"] == budgets[0]["score_s"] + budgets[1]["score_s"]
    tests = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert [line["step"] for line in tests if line["split"] == "test"] == [15, 30, 60]


@pytest.mark.parametrize("value", ["0.5", "[0.5,0.25]", "[0.25,0.25]", "[0,0.5]", "[0.5,1]", "[abc]", "[1.5]",
                                   "[-0.1]", "null", "[nan]", "automatic", "AUTO"])
def test_bad_budgets_are_refused_in_one_line_before_the_run_directory(tmp_path, tiny, value):
    result = run_nerfexp(*tiny, f"test_budgets={value}", f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    line = one_error_line(result)
    assert line.startswith("nerfexp: error: test_budgets=") and line.endswith(
        "expected auto, or a list of fractions of the steps, each a finite number > 0 and < 1, strictly increasing "
        "(e.g. [0.25, 0.5]; [] scores the end alone)"), line
    assert not (tmp_path / "run").exists()


def test_the_default_budgets_are_auto_a_quarter_and_a_half_where_their_cost_allows():
    assert tiny_config().test_budgets == AUTO and DEFAULT_FRACTIONS == (0.25, 0.5) and COST_SHARE == 0.25
    assert RunRecorder("unused", {}, test_budgets=AUTO).test_budgets == [0.25, 0.5]


@pytest.mark.parametrize(("pending", "cost_each_s", "spent_s", "training_s", "kept"), [
    (2, 240.0, 0.0, 100.0, 0),  # the issue's: 240 s a budget against 25 s (a quarter of 100 s): none
    (2, 10.0, 0.0, 100.0, 2),  # 20 s of 25 s: both
    (2, 12.5, 0.0, 100.0, 2),  # exactly 25 s: both (at most the share)
    (2, 13.0, 0.0, 100.0, 1),  # 26 s: one, 13 s
    (4, 10.0, 0.0, 100.0, 2),  # 25 s pays two of four
    (3, 10.0, 10.0, 100.0, 1),  # 10 s spent already: 15 s left, one
    (2, 10.0, 30.0, 100.0, 0),  # spent more than the share already
    (2, 2.0, 0.0, 1.0, 2),  # 4 s in all: under SMALL_COST_S (5 s), whatever the share
    (2, 3.0, 0.0, 1.0, 1),  # 6 s: 5 s pays one
    (2, 0.0, 0.0, 0.0, 2),  # costs nothing measurable
])
def test_auto_scores_as_many_budgets_as_a_quarter_of_the_training_pays_for(pending, cost_each_s, spent_s, training_s,
                                                                          kept):
    assert affordable_budgets(pending, cost_each_s, spent_s, training_s) == kept


@pytest.mark.parametrize(("elapsed_s", "step", "max_steps", "estimate_s"), [
    (25.0, 375, 1500, 100.0), (1.0, 15, 60, 4.0), (3.0, 30, 60, 6.0), (0.0, 1, 10, 0.0)])
def test_the_training_time_is_estimated_from_its_clock_at_the_step(elapsed_s, step, max_steps, estimate_s):
    assert training_estimate_s(elapsed_s, step, max_steps) == estimate_s


def planning(recorder: RunRecorder, step: int, max_steps: int, elapsed_s: float) -> types.SimpleNamespace:
    """A trainer of one process at ``step`` of ``max_steps``, ``recorder``'s clock at ``elapsed_s``."""
    recorder.elapsed_s = elapsed_s
    return types.SimpleNamespace(global_step=step, max_steps=max_steps, is_global_zero=True,
                                 strategy=types.SimpleNamespace(broadcast=lambda value, src: value))


@pytest.mark.parametrize(("scored", "cost_each_s", "paid", "dropped", "says"), [
    # 1,600 steps, budgets 1/8 to 3/4 (steps 200 to 1200), 25 s of training at step 200: 200 s estimated, 50 s for
    # the budgets in all
    ([], 20.0, False, {800, 1200}, "1/2, 3/4 not scored, the test views scored at 1/8, 1/4 and the end"),
    ([], 60.0, False, {200, 400, 800, 1200}, "1/8, 1/4, 1/2, 3/4 not scored, the test views scored at the end alone"),
    ([], 60.0, True, {400, 800, 1200}, "1/4, 1/2, 3/4 not scored, the test views scored at 1/8 and the end"),
    ([], 12.5, False, set(), None),  # 4 x 12.5 s: 50 s, the share exactly
    ([(100, 30.0)], 10.0, False, {800, 1200}, "the test views scored at 1/16, 1/8, 1/4 and the end"),
])
def test_auto_drops_the_latest_budgets_it_cannot_pay_for_in_one_line(caplog, scored, cost_each_s, paid, dropped,
                                                                     says):
    recorder = RunRecorder("unused", {}, test_budgets=AUTO)
    recorder.test_budgets = [0.0625, 0.125, 0.25, 0.5, 0.75]
    recorder.budgets = [{"step": step, "score_s": score_s} for step, score_s in scored]
    trainer = planning(recorder, 200, 1600, 25.0)
    with caplog.at_level("INFO", logger="nerfexp"):
        assert recorder._affordable(trainer, cost_each_s, "about N s (...)", paid) is (200 not in dropped)
    assert recorder.dropped == dropped
    lines = [record.getMessage() for record in caplog.records]
    if says is None:
        assert lines == []
    else:
        (line,) = lines
        assert line.startswith("test_budgets=auto: a budget's scoring is estimated at about N s (...), and the "
                               "budgets may cost 25% of the training's estimated 200 s in all: ") and says in line
    recorder._affordable(trainer, cost_each_s, "about N s (...)", paid)  # asked again: nothing more dropped or said
    assert recorder.dropped == dropped and len(caplog.records) == len(lines)


def test_a_users_list_is_scored_whatever_it_costs_and_says_so_once(caplog):
    recorder = RunRecorder("unused", {}, test_budgets=[0.25, 0.5])
    trainer = planning(recorder, 15, 60, 1.0)  # 4 s of training estimated
    with caplog.at_level("INFO", logger="nerfexp"):
        assert recorder._affordable(trainer, 2000.0, "about 2000 s (...)")
        assert recorder._affordable(planning(recorder, 30, 60, 2.0), 2000.0, "about 2000 s (...)")
    assert recorder.dropped == set()
    assert [record.getMessage() for record in caplog.records] == [
        "test_budgets=[0.25, 0.5]: a budget's scoring is estimated at about 2000 s (...), about 4000 s in all, more "
        "than 25% of the training's estimated 4 s: scored as set, outside the training clock (results.json's "
        "budget_scoring_s)"]


@pytest.fixture
def slow_views(monkeypatch) -> Callable[[float], None]:
    """Every test view's scoring made to take ``seconds`` on the clock (``time.perf_counter`` moved on as a test
    camera fitted per view would: no waiting); the budgets' cost is measured on that clock."""
    offset, real, scored = [0.0], time.perf_counter, NeRFModule.test_step
    monkeypatch.setattr(time, "perf_counter", lambda: real() + offset[0])

    def slow(seconds: float) -> None:
        def test_step(self, batch, batch_idx):
            offset[0] += seconds
            return scored(self, batch, batch_idx)
        monkeypatch.setattr(NeRFModule, "test_step", test_step)
    return slow


@pytest.mark.parametrize("budgets", ["auto", "[0.25,0.5]"])
def test_budgets_whose_scoring_costs_more_than_a_quarter_of_training_are_not_scored_under_auto_only(
        tmp_path, tiny, slow_views, budgets):
    # the case, on a clock: each test view costs 1000 s to score (two views: 2000 s a budget) against a
    # training of seconds. auto says so and scores the end alone, after paying for one view; a list is scored as set
    slow_views(1000.0)
    run_dir = tmp_path / "run"
    result = run_nerfexp(*tiny, f"test_budgets={budgets}", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    results = read_json(run_dir / "results.json")
    steps = [entry["step"] for entry in results["test_budgets"]]
    tests = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    cost = r"about 2000 s \(its first view took 1000\.\d\d s, x 2 views\)"  # 1000 s and the real seconds
    (said,) = [line for line in result.stdout.splitlines() if "test_budgets=" in line]
    if budgets == "auto":
        assert steps == [60] and results["budget_scoring_s"] == 0.0
        assert [line["step"] for line in tests if line["split"] == "test"] == [60]
        assert re.search(rf"test_budgets=auto: a budget's scoring is estimated at {cost}, and the budgets may cost "
                         r"25% of the training's estimated \d+ s in all: 1/4, 1/2 not scored, the test views scored at "
                         r"the end alone \(test_budgets=\[\.\.\.\] scores a list whatever it costs; "
                         r"docs/after-training\.md\)$", said), said
        assert "at a budget of" not in result.stdout
    else:
        assert steps == [15, 30, 60] and results["budget_scoring_s"] >= 4000.0
        assert re.search(rf"test_budgets=\[0\.25, 0\.5\]: a budget's scoring is estimated at {cost}, about 400\d s "
                         r"in all, more than 25% of the training's estimated \d+ s: scored as set", said), said
    assert results["train_time_s"] < 1000.0  # never in the training clock


@pytest.mark.slow
def test_a_protocol_that_fits_each_test_camera_scores_fewer_budgets_under_auto_with_a_line(tmp_path, tiny):
    # the protocol on a tiny run: each test camera refitted (100 Adam steps of 1,024 rays) costs several
    # times the whole training, so auto scores fewer budgets, said once, after the first view's fit
    run_dir = tmp_path / "run"
    result = run_nerfexp(*tiny, "camera_opt=so3xr3", "test_cameras=refined", f"hydra.run.dir={run_dir}",
                         cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    results = read_json(run_dir / "results.json")
    (line,) = [line for line in result.stdout.splitlines() if "test_budgets=auto" in line]
    assert "its first view took" in line and "x 2 views" in line and "not scored" in line
    # which of 1/4 and 1/2 fit in a quarter of the training depends on the machine's speed: not both
    scored_at = [entry["step"] for entry in results["test_budgets"]]
    assert scored_at in ([60], [15, 60]), scored_at
