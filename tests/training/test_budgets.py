"""Test scores at several budgets of one run (``test_budgets``, nerfexp.training.budgets): each budget's scores are
those ``nerfexp-eval`` gives the checkpoint of its step, scoring them changes nothing that is trained, and
``results.json`` lists them in step order with the final test's last, kept across a resume."""

import json
import math
import types
from pathlib import Path

import pytest
import torch

from nerfexp.training.budgets import budget_entry, budget_steps, budget_text, score_test_views, scoring_seconds
from nerfexp.training.recorders import RunRecorder
from tests.helpers import TINY, one_error_line, read_json, run_nerfexp

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
                                   "[-0.1]", "null", "[nan]"])
def test_bad_budgets_are_refused_in_one_line_before_the_run_directory(tmp_path, tiny, value):
    result = run_nerfexp(*tiny, f"test_budgets={value}", f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    line = one_error_line(result)
    assert line.startswith("nerfexp: error: test_budgets=") and line.endswith(
        "expected a list of fractions of the steps, each a finite number > 0 and < 1, strictly increasing (e.g. "
        "[0.25, 0.5]; [] scores the end alone)"), line
    assert not (tmp_path / "run").exists()
