"""Resuming and evaluating through the command line: a run killed half-way and resumed ends exactly
where the same run left alone ends; ``nerfexp-eval`` reproduces a run's own test scores."""

import json
import os
import shutil
import signal
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

import nerfexp.training.resume as resume
from nerfexp.errors import NerfexpError
from nerfexp.report.runs import read_run
from nerfexp.rundir.state import unfinished_line
from nerfexp.rundir.trained import current_settings, read_checkpoint
from nerfexp.training.recorders import keep_metrics_through
from tests.helpers import final_state, kill_at, one_error_line, read_json, run_nerfexp, tiny_config


def records(run_dir: Path) -> list[tuple]:
    return [(r["split"], r["step"], r["psnr"], r["ssim"])
            for r in map(json.loads, (run_dir / "metrics.jsonl").read_text().splitlines())]


@pytest.mark.slow
def test_a_killed_run_resumed_ends_as_the_uninterrupted_run(tiny_run, tmp_path, tiny):
    killed = run_nerfexp(*tiny, *kill_at(30), f"hydra.run.dir={tmp_path}", new_process=True, cwd=tmp_path)
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-3000:]
    assert not (tmp_path / "results.json").exists() and final_state(tmp_path)["step"] == 30
    assert read_json(tmp_path / "status.json")["state"] == "running"  # as a killed job leaves it
    # ... and read as what it is by every reader (nerfexp.rundir.state): the report, the commands reading it back
    assert read_run(tmp_path).state == "killed"
    assert unfinished_line(tmp_path, tmp_path / "checkpoints" / "last.ckpt", 30).startswith(
        f"the run in {tmp_path} was killed before it finished (process ")

    resumed = run_nerfexp(*tiny, f"resume={tmp_path}/checkpoints/last.ckpt", f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr[-3000:]

    alone, again = read_json(tiny_run / "results.json"), read_json(tmp_path / "results.json")
    assert again["steps"] == alone["steps"] == 60
    # Every batch, every jitter and every learning rate the same: on one machine the numbers are
    # bit-identical, not merely close (the weights after the last step are compared too).
    assert (again["test_psnr"], again["test_ssim"], again["val_psnr"]) == (
        alone["test_psnr"], alone["test_ssim"], alone["val_psnr"])
    assert records(tmp_path) == records(tiny_run)  # test 15, test 30, val 30, val 60, test 60
    # the budgets scored before the kill (1/4 and 1/2: steps 15 and 30) came back with the checkpoint, once each
    assert [(b["step"], b["test_psnr"], b["test_ssim"]) for b in again["test_budgets"]] == [
        (b["step"], b["test_psnr"], b["test_ssim"]) for b in alone["test_budgets"]]
    assert [b["step"] for b in again["test_budgets"]] == [15, 30, 60]
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
    result = run_nerfexp(str(tiny_run), new_process=True, cwd=tmp_path, script="nerfexp-eval")
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
        (path / ".hydra" / "config.yaml").write_text("model:\n  _target_: nerfexp.training.module.NeRFModule\n"
                                                     "  chunk: 8\n")
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


# the tiny run trains at the default precision (auto): what this machine chose ("{auto}" below, read from the run),
# and the other one ("{other}")
OTHER_PRECISION = {"bf16-mixed": "32-true", "32-true": "bf16-mixed"}


def files_of(folder: Path) -> dict:
    """Every file under ``folder`` and its bytes: to show that nothing was written, replaced or removed."""
    return {path.relative_to(folder): path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()}


@pytest.mark.parametrize(("overrides", "expected"), [
    (["seed=1", "scale.lr=0.01", "scale.steps=90"], "the checkpoint was trained with seed=0, scale.lr=0.005; this run "
                                                    "sets seed=1, scale.lr=0.01: resume with the checkpoint's settings "
                                                    "or start a new run"),
    # field=nerf: the tiny run's scale.depth, width and skips, which hashgrid's own field=ngp would leave unused
    (["encoding=hashgrid", "field=nerf", "scale.steps=90"], "the checkpoint was trained with encoding=posenc, "),
    (["scale.width=64", "scale.steps=90"],
     "the checkpoint was trained with scale.width=32; this run sets scale.width=64:"),
    (["trainer.precision={other}", "scale.steps=90"],
     "trained with trainer.precision={auto}; this run sets trainer.precision={other}:"),
    ([], "the checkpoint has taken 60 steps, all of this run's (scale.steps=60): raise scale.steps to train further, "
         "or score it with nerfexp-eval"),
])
def test_a_resume_that_would_not_continue_the_run_is_one_line_and_touches_nothing(tiny_run, tmp_path, tiny,
                                                                                   overrides, expected):
    run_dir = tmp_path / "run"
    shutil.copytree(tiny_run, run_dir)
    before = files_of(run_dir)
    checkpoint = run_dir / "checkpoints" / "last.ckpt"
    auto = read_json(run_dir / "results.json")["precision"]
    words = {"auto": auto, "other": OTHER_PRECISION[auto]}
    overrides, expected = [override.format(**words) for override in overrides], expected.format(**words)
    if not any(override.startswith("trainer.precision=") for override in overrides):
        # the checkpoint's own precision: another field (scale.width=64) is measured afresh by auto, which on a
        # busy machine (the suite's other worker) may choose otherwise, a second difference this case is not about
        overrides.append(f"trainer.precision={auto}")
    result = run_nerfexp(*tiny, *overrides, f"resume={checkpoint}", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    line = one_error_line(result)
    assert line.startswith(f"nerfexp: error: resume={checkpoint}: ") and expected in line, line
    assert files_of(run_dir) == before  # status.json still "finished", no second test line in metrics.jsonl


def test_another_network_size_in_a_checkpoint_that_records_no_settings_is_one_line(tiny_run, tmp_path, tiny):
    # an earlier nerfexp's checkpoint, outside any run directory: only the networks' shapes can tell
    state = torch.load(tiny_run / "checkpoints" / "last.ckpt", weights_only=True)
    del state["nerfexp_settings"]
    torch.save(state, tmp_path / "old.ckpt")
    result = run_nerfexp(*tiny, "scale.width=64", "scale.steps=90", f"resume={tmp_path / 'old.ckpt'}",
                         f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert one_error_line(result) == (
        f"nerfexp: error: {tmp_path / 'old.ckpt'}: not a checkpoint of this run's model: "
        "renderer.coarse.trunk.0.weight has shape [32, 63] there and [64, 63] in this run's model "
        "(another network size?)")
    assert not (tmp_path / "run" / "metrics.jsonl").exists()


@pytest.mark.parametrize(("make", "expected"), [
    ("random", "not a whole zip archive as torch.save writes"),
    ("empty", "an empty file"),
    ("truncated", "not a whole zip archive as torch.save writes"),
    ("text", "not a whole zip archive as torch.save writes"),
])
def test_a_file_that_is_not_a_checkpoint_is_one_line_without_torchs_advice(tiny_run, tmp_path, make, expected):
    real = (tiny_run / "checkpoints" / "last.ckpt").read_bytes()
    content = {"random": os.urandom(4096), "empty": b"", "truncated": real[:len(real) // 2],
               "text": b"model: not a checkpoint\n"}[make]
    path = tmp_path / "last.ckpt"
    path.write_bytes(content)
    with pytest.raises(NerfexpError) as raised:
        read_checkpoint(path)
    assert str(raised.value) == f"{path}: not a checkpoint ({expected}" + str(raised.value).split(expected, 1)[1]
    assert str(raised.value).endswith("nerfexp reads checkpoints as data only, never running code in them")
    assert "weights_only" not in str(raised.value) and "\n" not in str(raised.value)


def test_random_bytes_given_to_resume_are_one_line_and_nothing_is_made(tmp_path, tiny):
    (tmp_path / "last.ckpt").write_bytes(os.urandom(4096))
    result = run_nerfexp(*tiny, f"resume={tmp_path / 'last.ckpt'}", f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert one_error_line(result).startswith(f"nerfexp: error: {tmp_path / 'last.ckpt'}: not a checkpoint (")
    assert "weights_only" not in result.stderr and not (tmp_path / "run").exists()


def test_a_checkpoint_to_resume_is_read_once_while_unchanged_and_its_weights_not_kept(tmp_path, monkeypatch):
    # the Hydra callback and the job of a single run both ask for it (ResumeCheck, then train)
    path, reads = tmp_path / "last.ckpt", []

    def counted(checkpoint):
        reads.append(checkpoint)
        return read_checkpoint(checkpoint)

    monkeypatch.setattr(resume, "read_checkpoint", counted)
    torch.save({"state_dict": {"w": torch.ones(2, 3)}, "global_step": 7, "nerfexp_resumes": [{"step": 3}]}, path)
    first = resume.read_resumed(path)
    assert resume.read_resumed(path) is first and len(reads) == 1
    assert (first.step, first.settings, first.resumes) == (7, None, [{"step": 3}])
    assert first.weights["w"].shape == (2, 3) and first.weights["w"].is_meta  # shapes only, no values
    torch.save({"state_dict": {"w": torch.ones(4)}, "global_step": 9}, path)  # written again: read again
    assert resume.read_resumed(path).step == 9 and len(reads) == 2


def test_a_resume_keeps_the_metrics_lines_up_to_its_checkpoint(tmp_path):
    lines = [json.dumps({"step": step, "split": split, "psnr": 20.0 + step}) + "\n"
             for step, split in ((30, "val"), (60, "val"), (60, "test"), (90, "val"))]
    (tmp_path / "metrics.jsonl").write_text("".join(lines) + '{"step": 120, "spl')  # a last line cut short
    keep_metrics_through(tmp_path, 60)  # resumed at step 60: lines of later steps came from training redone
    assert (tmp_path / "metrics.jsonl").read_text() == "".join(lines[:3])
    unchanged = (tmp_path / "metrics.jsonl").stat().st_mtime_ns
    keep_metrics_through(tmp_path, 60)
    assert (tmp_path / "metrics.jsonl").stat().st_mtime_ns == unchanged  # nothing to drop: not rewritten


@pytest.mark.slow
def test_a_finished_run_trained_further_records_what_changed(tiny_run, tmp_path, tiny):
    run_dir = tmp_path / "run"
    shutil.copytree(tiny_run, run_dir)
    result = run_nerfexp(*tiny, "scale.steps=90", "model.chunk=100", f"resume={run_dir / 'checkpoints' / 'last.ckpt'}",
                         f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    results = read_json(run_dir / "results.json")
    assert results["steps"] == 90 and final_state(run_dir)["step"] == 90  # last.ckpt itself, not last-v1.ckpt
    (resume,) = results["resumes"]
    assert resume["step"] == 60 and resume["checkpoint"] == str((run_dir / "checkpoints" / "last.ckpt").resolve())
    # the learning-rate decay spans scale.steps: raised at step 60, it is recorded
    assert resume["changed"]["scale.steps"] == [60, 90] and resume["changed"]["model.chunk"] == [8192, 100]
    # the budgets of 1/4 and 1/2 of 60 steps (15, 30) kept; those of 90 (22, 45) lie before the checkpoint's step
    assert [(split, step) for split, step, *_ in records(run_dir)] == [
        ("test", 15), ("test", 30), ("val", 30), ("val", 60), ("test", 60), ("val", 90), ("test", 90)]
    assert records(run_dir)[:5] == records(tiny_run)  # the first 60 steps' lines as they were
    assert [budget["step"] for budget in results["test_budgets"]] == [15, 30, 90]
    assert torch.load(run_dir / "checkpoints" / "last.ckpt", weights_only=True)["nerfexp_resumes"] == [resume]


@pytest.mark.parametrize("hierarchical", [True, "proposal"])
def test_a_checkpoint_recorded_before_the_sampler_group_resumes_with_the_same_settings_and_names_a_changed_one(
        hierarchical):
    cfg = tiny_config(f"hierarchical={hierarchical}", "model.lpips=false")
    # the record a checkpoint of then holds: the renderer held the sampler's settings, and the scale group the hash
    # grid's sizes
    old = OmegaConf.to_container(cfg, resolve=False)
    del old["sampler"], old["model"]["renderer"]["sampler"]
    old["model"]["renderer"].update(hierarchical="${hierarchical}", n_coarse="${scale.n_coarse}",
                                    n_fine="${scale.n_fine}", n_single="${scale.n_single}", proposal="${proposal}")
    old["scale"].update(hash_log2_table_size=16, hash_finest=256)
    recorded = {"settings": resume.flat_settings(OmegaConf.create(old)), "choices": {}}
    assert "model.renderer.n_fine" in recorded["settings"]
    current = resume.flat_settings(cfg, skip=resume.may_differ)
    named_now = {**recorded, "settings": current_settings(recorded["settings"])}
    assert resume.differing(named_now, cfg, current, {}) == []
    assert resume.differing(recorded, cfg, current, {}) != []  # as recorded, the old names are not this run's
    changed = tiny_config(f"hierarchical={hierarchical}", "model.lpips=false", "scale.n_fine=8")
    found = resume.differing(named_now, changed, resume.flat_settings(changed, skip=resume.may_differ), {})
    assert [name for name, _, _ in found] == ["scale.n_fine"] and found[0][1:] == (16, 8)


@pytest.mark.parametrize("old", ["nerfexp.nerf.encodings.HashGridEncoding", "nerfexp.encodings.HashGridEncoding"])
def test_a_hash_grid_checkpoint_recorded_before_the_grid_had_its_own_module_resumes_with_the_same_settings(old):
    cfg = tiny_config("encoding=hashgrid", "model.lpips=false")
    current = resume.flat_settings(cfg, skip=resume.may_differ)
    # the record a checkpoint of then holds: the class where it lived, at every key that names it
    new = "nerfexp.nerf.hashgrid.HashGridEncoding"
    settings = {key: old if value == new else value for key, value in resume.flat_settings(cfg).items()}
    assert {key for key, value in settings.items() if value == old} >= {  # the proposal networks' grids too
        "model.renderer.field.position_encoding._target_", "encoding.position._target_"}
    recorded = {"settings": settings, "choices": {}}
    assert resume.differing(recorded, cfg, current, {}) != []  # as recorded, the old path is not this run's
    assert resume.differing({**recorded, "settings": current_settings(settings)}, cfg, current, {}) == []
