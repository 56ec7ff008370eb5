"""Camera refinement (``camera_opt=so3xr3``) through the real command line: the pose correction trains in its own
parameter group with its own schedule, the first view stays pinned, the refined poses are written into the run
and read back for its training cameras; perturbed training poses are brought toward the truth (slow)."""

import json

import pytest
import torch

from nerfexp.products.trained import RefinedScene, load_run, run_scene
from nerfexp.rundir.layout import REFINED_POSES
from nerfexp.rundir.trained import read_refined_poses
from tests.helpers import TINY, run_nerfexp

NOISE = "datamodule.pose_noise=[2,0.02]"


def test_a_refined_run_writes_its_cameras_and_the_commands_read_them_back(tmp_path):
    run_dir = tmp_path / "run"
    # a warm-up shorter than the tiny run (so3xr3's own, 300 steps, is longer): its rate ends at lr_final
    result = run_nerfexp(*TINY, "camera_opt=so3xr3", "camera_opt.correction.warmup_steps=10", NOISE,
                         "test_cameras=refined", "test_cameras.fit.steps=4",
                         "logger=none", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    results = json.loads((run_dir / "results.json").read_text())
    assert results["test_cameras"] == "refined"  # each test camera refined, and by how much
    assert len(results["test_camera_fit_deg_per_view"]) == 2 and results["test_camera_fit_deg"] > 0
    record = json.loads((run_dir / REFINED_POSES).read_text())
    refined, initial = torch.tensor(record["c2w"]), torch.tensor(record["initial_c2w"])
    assert refined.shape == initial.shape == (12, 4, 4)  # data.n_train=12
    assert torch.equal(refined[0], initial[0])  # the gauge: view 0's correction is pinned at zero
    assert not torch.equal(refined[1:], initial[1:])  # the others moved
    assert record["pose_noise"] == [2.0, 0.02]
    assert set(record["errors"]) == {"before", "after"}
    assert 1.0 < record["errors"]["before"]["rotation_deg"] <= 2.0

    run = load_run(run_dir)
    checkpoint = torch.load(run.checkpoint, weights_only=True)
    groups = checkpoint["optimizer_states"][0]["param_groups"]
    assert [g["lr"] for g in groups][-1] == pytest.approx(1e-5)  # the pose group ends at its own lr_final
    assert torch.allclose(run.module.camera_opt.corrections()[1:], checkpoint["state_dict"]["camera_opt.delta"])
    scene = run_scene(run_dir, run.cfg)
    assert isinstance(scene, RefinedScene)
    assert torch.allclose(scene.views("train").c2w.double(), read_refined_poses(run_dir), atol=1e-6)
    assert torch.equal(scene.views("test").c2w, scene.scene.views("test").c2w)  # evaluation cameras untouched


def test_without_camera_opt_nothing_is_built_or_written(tmp_path):
    run_dir = tmp_path / "run"
    result = run_nerfexp(*TINY, "logger=none", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert json.loads((run_dir / "results.json").read_text())["test_cameras"] == "given"
    run = load_run(run_dir)
    assert run.module.camera_opt is None
    assert not (run_dir / REFINED_POSES.parent).exists()
    assert not any("camera_opt" in key or "window" in key for key in run.module.state_dict())
    assert list(run.module.named_parameter_groups()) == ["networks"]
    assert not isinstance(run_scene(run_dir, run.cfg), RefinedScene)


@pytest.mark.parametrize("override, line", [
    ("camera_opt=so3xr3", "camera_opt=so3xr3: the corrections move world rays, and data.ndc=true trains on NDC rays; "
                          "set data.ndc=false (with data.near and data.far) to refine an LLFF scene's cameras"),
    ("test_cameras=refined", "test_cameras=refined: the fit turns and moves world rays, and data.ndc=true scores NDC "
                             "rays; set data.ndc=false (with data.near and data.far), or test_cameras=given"),
])
def test_refining_cameras_on_ndc_rays_is_refused_in_one_line(tmp_path, override, line):
    result = run_nerfexp(override, "data=llff", "data.root=/nowhere", f"hydra.run.dir={tmp_path}/r", cwd=tmp_path)
    assert result.returncode == 1
    assert result.stderr.strip().splitlines()[-1] == f"nerfexp: error: {line}"


# Training poses perturbed by 2 degrees and 2% of the cameras' radius, refined with the scene for 1,000 steps of a
# tiny network on 16 views of 24 x 24 pixels (positions encoded at 1/8 scale, the pose rate ramped over 300 steps).
# Measured (errors after aligning the centres, mean over the 16 views; seed: before -> after):
#   seed 0: rotation 2.004 -> 1.400 deg (1.43x), centre 0.0685 -> 0.0632 (1.08x)
#   seed 1: rotation 1.870 -> 1.206 deg (1.55x), centre 0.0672 -> 0.0622 (1.08x)
# Required: rotation errors shrink by at least 1.25x; centre errors do not grow (at 24 pixels a centre moved across
# the view is nearly a turn of the camera, and the two trade off). One seed runs here (the suite's time); both held.
REFINE = ["scale.steps=1000", "scale.val_every=1000", "scale.batch_rays=256", "scale.depth=2", "scale.width=32",
          "scale.skips=[1]", "scale.view_hidden=16", "scale.n_coarse=16", "scale.n_fine=16", "scale.image_size=24",
          "scale.position_input_scale=0.125", "data.n_train=16", "data.n_val=1", "data.n_test=4",
          "trainer.enable_progress_bar=false", "trainer.precision=32-true", "logger=none", "model.lpips=false",
          "camera_opt=so3xr3", "camera_opt.correction.warmup_steps=300", NOISE]
ROTATION_SHRINK = 1.25


@pytest.mark.slow
def test_perturbed_training_poses_are_brought_toward_the_truth(tmp_path):
    run_dir = tmp_path / "run"
    result = run_nerfexp(*REFINE, "seed=0", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    errors = json.loads((run_dir / REFINED_POSES).read_text())["errors"]
    before, after = errors["before"], errors["after"]
    assert before["rotation_deg"] / after["rotation_deg"] >= ROTATION_SHRINK, errors
    assert after["centre"] <= before["centre"], errors


@pytest.mark.parametrize(("overrides", "window", "warmup"), [
    ([], 0.0, None),  # the paper's NeRF: no window, no corrections
    (["camera_opt=so3xr3"], 0.5, 300),  # the measured best schedule (docs/results/camera_opt_schedules.md)
    (["camera_opt=so3xr3", "encoding.position.coarse_to_fine=0.2"], 0.2, 300),  # the command line wins
    (["camera_opt=so3xr3", "camera_opt.coarse_to_fine=0"], 0.0, 300),  # camera_opt's own key, read by the encoding
])
def test_camera_refinement_asks_the_positional_encoding_for_barfs_window(overrides, window, warmup):
    from hydra import compose, initialize_config_module

    with initialize_config_module("nerfexp.conf", version_base=None):
        cfg = compose("config", overrides=overrides)
    assert cfg.encoding.position.coarse_to_fine == window
    assert (cfg.camera_opt.correction and cfg.camera_opt.correction.warmup_steps) == warmup
