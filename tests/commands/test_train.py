"""The command line as a user runs it: a whole training run, the README's multirun, bad input."""

import hashlib
import json
import math
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from PIL import Image

from nerfexp.commands.train import recorded_choices, sweep_objective
from nerfexp.data.procedural import load_procedural, scene_cameras
from nerfexp.pixels import to_uint8
from nerfexp.scoring.metrics import psnr
from tests.helpers import TINY_SINGLE, read_json, run_nerfexp


def blank_psnr(n_test: int, size: int) -> float:
    """PSNR of an all-white (empty scene) prediction on the built-in scene's test views."""
    views = load_procedural("test", n_test, size, size)
    targets = views.rgb_on(torch.ones(3))
    return sum(psnr(torch.ones_like(t), t) for t in targets) / len(targets)


@pytest.mark.slow
def test_a_short_run_learns_the_scene_and_writes_every_output(tmp_path):
    overrides = ["scale.steps=400", "scale.val_every=200", "scale.batch_rays=512", "scale.depth=3",
                 "scale.width=64", "scale.skips=[2]", "scale.view_hidden=32", "scale.n_coarse=24",
                 "scale.n_fine=24", "scale.image_size=32", "data.n_train=40", "data.n_test=2",
                 "trainer.enable_progress_bar=false", f"hydra.run.dir={tmp_path}"]
    result = run_nerfexp(*overrides, new_process=True, cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    results = read_json(tmp_path / "results.json")
    # Not an empty scene: an all-white image scores about 9 dB here; the threshold asks for +6 dB.
    baseline = blank_psnr(2, 32)
    assert results["test_psnr"] > baseline + 6, (results["test_psnr"], baseline)
    assert 0 < results["test_ssim"] <= 1 and results["steps"] == 400 and results["n_params"] > 0
    assert results["collapse"] is None  # nor a false alarm: the guard judged the validation of step 200 too
    assert results["choices"] == {"encoding": "posenc", "view_dependence": "mlp", "data": "procedural",
                                  "field": "nerf", "optimizer": "adam", "scale": "cpu", "trainer": "default",
                                  "acceleration": "none", "contraction": "none", "appearance": "none",
                                  "camera_opt": "off", "test_cameras": "given", "callbacks": "default",
                                  "logger": "tensorboard", "sampler": "paper",
                                  "hierarchical": True, "seed": 0}
    # the test scored the checkpoint this run wrote, and says which, by path and content
    written = tmp_path / "checkpoints" / "last.ckpt"
    assert results["checkpoint"] == {"path": "checkpoints/last.ckpt",
                                     "sha256": hashlib.sha256(written.read_bytes()).hexdigest()}
    records = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    # the test views scored at the default budgets too, a quarter and a half of the steps (test_budgets)
    assert [(r["split"], r["step"]) for r in records] == [("test", 100), ("test", 200), ("val", 200), ("val", 400),
                                                          ("test", 400)]
    assert all(math.isfinite(r["psnr"]) and math.isfinite(r["ssim"]) and r["wall_time_s"] > 0 for r in records)
    assert records[1]["wall_time_s"] > records[0]["wall_time_s"]
    for name in ("r_0.png", "r_0_depth.png", "r_0_target.png", "r_0_error.png", "r_1.png"):
        assert (tmp_path / "test" / name).stat().st_size > 0
    assert list((tmp_path / "tensorboard").glob("events.out.tfevents.*"))
    assert (tmp_path / "checkpoints" / "last.ckpt").exists()


def test_the_last_step_is_validated_and_each_test_view_is_saved_with_its_target_and_error(tmp_path, tiny):
    # 40 steps, validation every 30: Lightning alone would validate at step 30 only
    result = run_nerfexp(*tiny, "scale.steps=40", "scale.val_every=30", f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    records = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    records = [r for r in records if r["step"] > 20]  # the test lines of the default budgets (10, 20) aside
    assert [(r["split"], r["step"]) for r in records] == [("val", 30), ("val", 40), ("test", 40)]
    results = read_json(tmp_path / "results.json")
    assert results["val_psnr"] == records[1]["psnr"] and results["steps"] == 40
    # one log line per validation: its step, PSNR and SSIM
    lines = [line for line in (tmp_path / "nerfexp.log").read_text().splitlines() if "validation PSNR" in line]
    assert [line.split("step ")[1].split(":")[0] for line in lines] == ["30/40", "40/40"]
    assert f"{records[1]['psnr']:.2f} dB, SSIM {records[1]['ssim']:.4f}" in lines[1]

    # per view: the scores in view order, whose mean is the reported mean
    assert results["test_views"] == [0, 1]  # data.n_test=2
    assert np.mean(results["test_psnr_per_view"]) == pytest.approx(results["test_psnr"], abs=1e-12)
    assert np.mean(results["test_ssim_per_view"]) == pytest.approx(results["test_ssim"], abs=1e-12)
    # the saved target is the scene's own test view; the error image is |render - target| (8-bit rounding apart)
    truth = load_procedural("test", 2, 24, 24).rgb_on(torch.ones(3))  # TINY: 24 x 24, white background
    for view, score in zip(results["test_views"], results["test_psnr_per_view"], strict=True):
        read = {suffix: np.asarray(Image.open(tmp_path / "test" / f"r_{view}{suffix}.png"), dtype=np.int16)
                for suffix in ("", "_target", "_error")}
        assert np.array_equal(read["_target"], to_uint8(truth[view]))
        assert np.abs(read["_error"] - np.abs(read[""] - read["_target"])).max() <= 1
        mse = np.mean(((read[""] - read["_target"]) / 255.0) ** 2)
        assert -10 * np.log10(mse) == pytest.approx(score, abs=0.3)  # from the 8-bit files: rounding apart


@pytest.mark.slow
def test_readme_multirun_trains_four_variants(tmp_path, tiny):
    result = run_nerfexp("-m", "encoding=none,posenc", "hierarchical=true,false", *tiny, TINY_SINGLE,
                         f"hydra.sweep.dir={tmp_path}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    results = [read_json(p) for p in sorted(tmp_path.glob("*/results.json"))]
    assert len(results) == 4
    combos = {(r["choices"]["encoding"], r["choices"]["hierarchical"]) for r in results}
    assert combos == {("none", True), ("none", False), ("posenc", True), ("posenc", False)}
    for r in results:
        assert math.isfinite(r["test_psnr"]) and math.isfinite(r["test_ssim"])
        assert r["evaluations_per_ray"] == 48  # 16 + (16 + 16) with hierarchy, n_single = 48 without
        # each job was given a sample count it does not use (a legitimate sweep): recorded as null, not as set
        config, hierarchical = r["config"], r["choices"]["hierarchical"]
        unused = ["n_single"] if hierarchical else ["n_coarse", "n_fine"]
        used = ["n_coarse", "n_fine"] if hierarchical else ["n_single"]
        sampler = config["model"]["renderer"]["sampler"]
        assert all(config["scale"][k] is None and config["sampler"][k] is None and sampler[k] is None for k in unused)
        assert all(config["scale"][k] == config["sampler"][k] == sampler[k] > 0 for k in used)
    log = (tmp_path / "0" / "nerfexp.log").read_text()
    assert "scale.n_single=48: not used with hierarchical=true" in log
    report = run_nerfexp(str(tmp_path), cwd=tmp_path, script="nerfexp-report")
    assert report.returncode == 0, report.stderr[-3000:]
    assert "Runs: 4 (4 finished)" in (tmp_path / "report.md").read_text()  # the null records read back


def test_unknown_component_is_named(tmp_path):
    result = run_nerfexp("encoding=posenk", new_process=True, cwd=tmp_path)
    assert result.returncode == 1
    assert result.stderr == "nerfexp: error: encoding=posenk: no such option (choose from hashgrid, none, posenc)\n"


def test_config_typo_is_named(tmp_path):
    result = run_nerfexp("trainer.max_step=3", cwd=tmp_path)
    assert result.returncode != 0 and "trainer.max_step" in result.stderr


def test_blender_without_root_says_which_key(tmp_path):
    result = run_nerfexp("data=blender", f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    assert result.returncode != 0 and "data.root" in result.stderr
    assert "Traceback" not in result.stderr


def test_missing_dataset_folder_is_one_clear_line(tmp_path):
    missing = tmp_path / "no_such_scene"
    result = run_nerfexp("data=blender", f"data.root={missing}", f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert result.returncode != 0
    assert str(missing) in result.stderr and "Traceback" not in result.stderr


@pytest.mark.slow
def test_a_blender_format_scene_written_by_the_exporter_trains(tmp_path, tiny):
    scene = tmp_path / "scene"
    exported = run_nerfexp(str(scene), "--resolution", "24", "--n-train", "10", "--n-val", "1", "--n-test", "2",
                           new_process=True, cwd=tmp_path, script="nerfexp-scene")
    assert exported.returncode == 0, exported.stderr[-2000:]
    overrides = [o for o in tiny if not o.startswith(("data.", "scale.image_size"))]
    result = run_nerfexp("data=blender", f"data.root={scene}", "data.downscale=2", "data.n_val=1", "data.test_stride=1",
                         *overrides, f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    results = read_json(tmp_path / "run" / "results.json")
    assert results["choices"]["data"] == "blender" and math.isfinite(results["test_psnr"])
    assert sorted(p.name for p in (tmp_path / "run" / "test").glob("r_?.png")) == ["r_0.png", "r_1.png"]


def test_a_run_into_a_directory_that_holds_another_run_stops_before_any_work(tiny_run, tmp_path, tiny):
    kept = {name: (tiny_run / name).read_bytes() for name in (".hydra/config.yaml", "status.json", "results.json")}
    result = run_nerfexp(*tiny, "seed=1", f"hydra.run.dir={tiny_run}", cwd=tmp_path)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 1 and len(lines) == 1, result.stderr[-2000:]
    assert lines[0].startswith(f"nerfexp: error: {tiny_run} holds a finished run (") and "resume=" in lines[0]
    assert {name: (tiny_run / name).read_bytes() for name in kept} == kept  # nothing of that run touched
    assert not (tiny_run / "checkpoints" / "last-v1.ckpt").exists()


def test_a_sweep_into_a_directory_that_holds_an_earlier_sweep_stops(tiny_run, tmp_path, tiny):
    sweep = tmp_path / "sweep"
    (sweep / "0").mkdir(parents=True)
    (sweep / "0" / "status.json").write_bytes((tiny_run / "status.json").read_bytes())
    result = run_nerfexp("-m", *tiny, "seed=0,1", f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert result.returncode == 1 and result.stderr.strip() == (
        f"nerfexp: error: {sweep} holds the runs of an earlier sweep (1): choose another directory "
        "(hydra.sweep.dir=...)"), result.stderr[-2000:]
    assert sorted(p.name for p in sweep.iterdir()) == ["0"]


def test_default_run_directories_of_runs_started_at_once_differ(tmp_path):
    # two commands started together (most often in the same second): their default directories
    # (outputs/DATE/HH-MM-SS-MICROSECONDS) differ
    def default_dir(_) -> str:
        shown = run_nerfexp("--cfg", "hydra", "--resolve", new_process=True, cwd=tmp_path)
        lines = shown.stdout.splitlines()
        return next(line.split("dir: ")[1] for line in lines if line.startswith("    dir: outputs/"))

    with ThreadPoolExecutor(2) as pool:
        first, second = pool.map(default_dir, range(2))
    assert first != second
    for shown in (first, second):
        date, time_of_day = shown.split("/")[1:]
        assert len(date) == len("2026-11-23") and len(time_of_day) == len("10-00-00-123456")


@pytest.mark.slow
def test_lpips_is_recorded_in_every_file_where_alexnets_weights_are_given(tmp_path, tiny, monkeypatch):
    from nerfexp.scoring import perceptual
    from nerfexp.scoring.perceptual import LpipsScorer, lpips_network
    from tests.scoring.alexnet import alexnet_state, stand_in
    from tests.scoring.weights_server import hashed_name, refused_url

    weights, run = tmp_path / "alexnet.pth", tmp_path / "run"
    torch.save(alexnet_state(), weights)  # made here: no test reads the ImageNet weights
    published = stand_in(monkeypatch, weights)  # standing in for them
    # threads=1: one thread count for the run's renders and nerfexp-eval's (which runs in this process after it),
    # not the count the auto setting follows the machine's load to: a render made with another count may round a
    # pixel of its 8-bit image the other way, and the LPIPS compared exactly below with it
    result = run_nerfexp(*tiny, "scale.image_size=32", "model.lpips=true", f"model.lpips_weights={weights}",
                         "threads=1", f"hydra.run.dir={run}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    results = read_json(run / "results.json")
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    # the default budgets (steps 15 and 30) score LPIPS as the final test does
    assert [r["split"] for r in records] == ["test", "test", "val", "val", "test"]
    assert all(r["lpips"] > 0 for r in records)
    assert [b["test_lpips"] for b in results["test_budgets"]] == [records[0]["lpips"], records[1]["lpips"],
                                                                  results["test_lpips"]]
    assert records[-1]["lpips"] == results["test_lpips"] == pytest.approx(np.mean(results["test_lpips_per_view"]))
    # each view's score is LPIPS of the saved 8-bit render against its saved target
    scorer = LpipsScorer(lpips_network(weights))
    for view, score in zip(results["test_views"], results["test_lpips_per_view"], strict=True):
        render, target = (torch.from_numpy(np.asarray(Image.open(run / "test" / f"r_{view}{suffix}.png"),
                                                      dtype=np.float32) / 255) for suffix in ("", "_target"))
        assert scorer(render, target) == pytest.approx(score, rel=1e-4)
    log = (run / "nerfexp.log").read_text()
    assert f"LPIPS {records[2]['lpips']:.4f} after" in log and f"LPIPS {results['test_lpips']:.4f} after 60" in log
    assert results["lpips_weights_sha256"] == published
    # nerfexp-eval scores the checkpoint with the run's config, the LPIPS weights the evaluating user's: none of
    # the run's (an empty hub cache, offline) ...
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.setattr(perceptual, "ALEXNET_URL", refused_url(hashed_name("alexnet-owt", weights.read_bytes())))
    evaluated = run_nerfexp(str(run), cwd=tmp_path, script="nerfexp-eval")
    assert evaluated.returncode == 0, evaluated.stderr[-3000:]
    assert not [key for key in read_json(run / "eval.json") if "lpips" in key]
    # ... and the same file named by the evaluating user: the same LPIPS
    evaluated = run_nerfexp(str(run), f"model.lpips_weights={weights}", cwd=tmp_path, script="nerfexp-eval")
    assert evaluated.returncode == 0, evaluated.stderr[-3000:]
    scores = read_json(run / "eval.json")
    assert scores["test_lpips_per_view"] == results["test_lpips_per_view"]
    assert scores["lpips_weights_sha256"] == published
    assert f"LPIPS {scores['test_lpips']:.4f} of " in evaluated.stdout


@pytest.mark.slow
def test_own_weights_are_recorded_as_lpips_custom_with_their_digest(tmp_path, tiny):
    from tests.scoring.alexnet import alexnet_state

    weights, run = tmp_path / "mine.pth", tmp_path / "run"
    torch.save(alexnet_state(seed=4), weights)
    refused = run_nerfexp(*tiny, "scale.image_size=32", f"model.lpips_weights={weights}", f"hydra.run.dir={run}",
                          cwd=tmp_path)
    assert refused.returncode == 1 and not run.exists()  # not the published weights: refused before any work
    assert f"{weights}: not torchvision's AlexNet ImageNet weights" in refused.stderr
    result = run_nerfexp(*tiny, "scale.image_size=32", f"model.lpips_weights={weights}", "model.lpips_custom=true",
                         f"hydra.run.dir={run}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    results = read_json(run / "results.json")
    assert not [key for key in results if key.startswith("test_lpips") and "custom" not in key]
    assert results["test_lpips_custom"] == pytest.approx(np.mean(results["test_lpips_custom_per_view"]))
    assert results["lpips_weights_sha256"] == hashlib.sha256(weights.read_bytes()).hexdigest()
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert all("lpips" not in r and r["lpips_custom"] > 0 for r in records)
    assert "LPIPS with your own weights (not comparable)" in (run / "nerfexp.log").read_text()


def test_a_run_without_lpips_records_none_and_says_why_in_one_line(tiny_run):
    # TINY's 24-pixel images are below AlexNet's 31, and CI has no AlexNet weights: either way, one line
    results = read_json(tiny_run / "results.json")
    assert not [key for key in results if "lpips" in key]
    assert not [r for r in map(json.loads, (tiny_run / "metrics.jsonl").read_text().splitlines()) if "lpips" in r]
    lines = [line for line in (tiny_run / "nerfexp.log").read_text().splitlines() if "LPIPS" in line]
    assert len(lines) == 1 and "LPIPS not scored: " in lines[0], lines


def test_a_run_records_the_check_that_its_test_views_are_unseen(tiny_run):
    # TINY's scene: the built-in cameras of 12 training, 1 validation and 2 test views, none near another split's
    centres = torch.cat([scene_cameras(split, n)[:, :3, 3] for split, n in (("train", 12), ("val", 1), ("test", 2))])
    centres = centres.float().double().numpy()  # as the views hold them
    spread = float(np.sqrt(np.mean(np.sum((centres - centres.mean(0)) ** 2, -1))))
    assert read_json(tiny_run / "results.json")["split_check"] == {
        "centre_fraction": 0.01, "centre_spread": pytest.approx(spread, rel=1e-9), "ray_degrees": 0.5,
        "image_psnr_db": 20.0, "views": 15, "image_pairs": 0}


def test_a_sweeper_never_takes_a_run_that_rendered_nothing_for_its_best():
    assert sweep_objective({"val_psnr": 14.71, "collapse": None}) == 14.71
    collapsed = sweep_objective({"val_psnr": 14.71, "collapse": "every test view rendered nothing (...)"})
    assert collapsed == -math.inf and collapsed < sweep_objective({"val_psnr": -300.0, "collapse": None})


def test_results_record_each_groups_option_but_hydras_and_empty_groups_with_hierarchical_and_seed():
    cfg = OmegaConf.create({"hierarchical": False, "seed": 7})
    choices = OmegaConf.create({"data": "procedural", "hydra/launcher": "basic", "hydra/output": "default",
                                "sweeps": None, "sampler": "uniform", "acceleration": "occupancy",
                                "encoding": "hashgrid", "acceleration/by_encoding": "occupancy_hashgrid"})
    # acceleration/by_encoding is chosen by config.yaml from the two choices beside it: no one's choice, not recorded
    assert recorded_choices(cfg, choices) == {"data": "procedural", "sampler": "uniform", "acceleration": "occupancy",
                                              "encoding": "hashgrid", "hierarchical": False, "seed": 7}
