"""Resuming and evaluating through the command line: a run killed half-way and resumed ends exactly
where the same run left alone ends; ``nerfexp-eval`` reproduces a run's own test scores."""

import json
import signal
from pathlib import Path

import pytest
import torch

from tests.helpers import final_state, kill_at, read_json, run_nerfexp


def records(run_dir: Path) -> list[tuple]:
    return [(r["split"], r["step"], r["psnr"], r["ssim"])
            for r in map(json.loads, (run_dir / "metrics.jsonl").read_text().splitlines())]


@pytest.mark.slow
def test_a_killed_run_resumed_ends_as_the_uninterrupted_run(tiny_run, tmp_path, tiny):
    killed = run_nerfexp(*tiny, *kill_at(30), f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-3000:]
    assert not (tmp_path / "results.json").exists() and final_state(tmp_path)["step"] == 30
    assert read_json(tmp_path / "status.json")["state"] == "running"  # as a killed job leaves it

    resumed = run_nerfexp(*tiny, f"resume={tmp_path}/checkpoints/last.ckpt", f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr[-3000:]

    alone, again = read_json(tiny_run / "results.json"), read_json(tmp_path / "results.json")
    assert again["steps"] == alone["steps"] == 60
    # Every batch, every jitter and every learning rate the same: on one machine the numbers are
    # bit-identical, not merely close (the weights after the last step are compared too).
    assert (again["test_psnr"], again["test_ssim"], again["val_psnr"]) == (
        alone["test_psnr"], alone["test_ssim"], alone["val_psnr"])
    assert records(tmp_path) == records(tiny_run)  # val 30, val 60, test 60
    state, expected = final_state(tmp_path), final_state(tiny_run)
    assert state["lr"] == expected["lr"] and state["step"] == expected["step"] == 60
    assert state["weights"].keys() == expected["weights"].keys()
    assert all(torch.equal(state["weights"][k], expected["weights"][k]) for k in expected["weights"])
    assert all(torch.equal(state["adam"][i]["exp_avg_sq"], expected["adam"][i]["exp_avg_sq"]) for i in expected["adam"])
    # the clock kept counting across the kill: training seconds include those before it
    first_half_s = json.loads((tmp_path / "metrics.jsonl").read_text().splitlines()[0])["wall_time_s"]  # val 30
    assert again["train_time_s"] > first_half_s > 0


@pytest.mark.slow
def test_an_evaluation_reproduces_the_runs_test_scores(tiny_run, tmp_path):
    result = run_nerfexp(str(tiny_run), cwd=tmp_path, script="nerfexp-eval")
    assert result.returncode == 0, result.stderr[-3000:]
    scores, results = read_json(tiny_run / "eval.json"), read_json(tiny_run / "results.json")
    # the same weights, views and chunking as the run's own final test: the same numbers exactly
    assert (scores["test_psnr"], scores["test_ssim"]) == (results["test_psnr"], results["test_ssim"])
    assert scores["step"] == 60 and scores["test_views"] == results["test_views"] == [0, 1]  # data.n_test=2
    for name in ("test_psnr_per_view", "test_ssim_per_view"):
        assert scores[name] == results[name]
    assert sum(scores["test_psnr_per_view"]) / 2 == pytest.approx(scores["test_psnr"], abs=1e-12)
    assert "test PSNR" in result.stdout and str(tiny_run / "eval.json") in result.stdout

    (tiny_run / "eval.json").unlink()  # a checkpoint path works as well as the run directory
    checkpoint = tiny_run / "checkpoints" / "last.ckpt"
    by_path = run_nerfexp(str(checkpoint), "model.chunk=100", cwd=tmp_path, script="nerfexp-eval")
    assert by_path.returncode == 0, by_path.stderr[-3000:]
    again = read_json(tiny_run / "eval.json")
    assert again["checkpoint"] == str(checkpoint.resolve())
    assert again["test_psnr"] == pytest.approx(results["test_psnr"], abs=1e-4)  # other chunks: rounding only
    assert again["test_ssim"] == pytest.approx(results["test_ssim"], abs=1e-5)


@pytest.mark.parametrize("make", ["nothing", "not_a_run", "no_checkpoint", "typo_override"])
def test_eval_of_a_missing_run_is_one_clear_line(tmp_path, make):
    path, extra = tmp_path / "run", []
    if make != "nothing":
        path.mkdir()
    if make in ("no_checkpoint", "typo_override"):
        (path / ".hydra").mkdir()
        (path / ".hydra" / "config.yaml").write_text("model:\n  chunk: 8\n")
    if make == "typo_override":
        (path / "checkpoints").mkdir()
        (path / "checkpoints" / "last.ckpt").write_bytes(b"")
        extra = ["model.chunks=7"]
    result = run_nerfexp(str(path), *extra, cwd=tmp_path, script="nerfexp-eval")
    assert result.returncode == 1 and "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    expected = {"nothing": str(path), "not_a_run": ".hydra/config.yaml", "no_checkpoint": "last.ckpt",
                "typo_override": "model.chunks"}[make]
    assert len(lines) == 1 and lines[0].startswith("nerfexp-eval: error: ") and expected in lines[0], lines
