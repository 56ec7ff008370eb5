"""The appearance axis end to end: a sweep of appearance=none,embedding on the built-in scene whose images each have
their own exposure and white balance (data.appearance_changes=all), scored on the same pixels and reported."""

import json

import pytest
import torch

from nerfexp.data.procedural import EXPOSURE_STOPS, WHITE_BALANCE_STOPS, ProceduralScene, appearance_gains
from nerfexp.rundir.layout import REFINED_POSES
from tests.helpers import TINY, final_state, kill_at, read_json, run_nerfexp

# A small model that learns the scene's shapes within 600 steps (one network of 32 samples per ray, 32 x 32 images),
# so that what the images' appearance costs is more than the seeds' noise.
SMALL = ["scale.steps=600", "scale.val_every=600", "scale.lr_warmup_steps=20", "scale.batch_rays=256",
         "scale.depth=2", "scale.width=64", "scale.skips=[1]", "scale.view_hidden=32", "hierarchical=false",
         "scale.n_single=32", "scale.image_size=32", "data.n_train=20", "data.n_val=1", "data.n_test=4",
         "data.appearance_changes=all", "model.lpips=false", "logger=none", "trainer.enable_progress_bar=false"]


@pytest.mark.parametrize("changes, varied", [("none", ()), ("train", ("train",)), ("all", ("train", "test"))])
def test_the_scenes_images_take_their_known_gains_clipped_and_the_others_stay_neutral(changes, varied):
    gains = appearance_gains(200, seed=0)
    stops = torch.log2(gains)
    assert stops.max() <= EXPOSURE_STOPS + WHITE_BALANCE_STOPS and stops.min() >= -EXPOSURE_STOPS - WHITE_BALANCE_STOPS
    assert stops.max() > 1.2 and stops.min() < -1.2  # the range is used: brighter and darker images alike
    plain, changed = (ProceduralScene(image_size=8, n_train=3, n_test=2, appearance_changes=c)
                      for c in ("none", changes))
    for split, seed in (("train", 0), ("test", 2)):
        before, after = plain.views(split).rgba, changed.views(split).rgba
        expected = (before[..., :3] * appearance_gains(len(before), seed)[:, None, None]).clamp(0, 1)
        assert torch.equal(after[..., :3], expected if split in varied else before[..., :3])
        assert torch.equal(after[..., 3], before[..., 3])  # alpha unchanged: the background stays the scene's


@pytest.mark.slow
def test_the_embedding_scores_higher_under_nerfws_protocol_on_images_of_varied_appearance(tmp_path):
    # Measured before fixing the threshold (test PSNR of the right halves, dB; 2 CPU threads' worth of a shared
    # machine, about 25 s per run): seed 0: none 18.73, embedding 19.55 (+0.83); seed 1: none 18.73, embedding 19.57
    # (+0.85). The embedding's whole image with the mean code scored 18.47 and 18.60, as none's 18.35 and 18.33: it
    # is the code fitted on the left half that recovers each test image's own exposure. Threshold: half the margin.
    sweep = tmp_path / "sweep"
    result = run_nerfexp("-m", *SMALL, "appearance=none,embedding", f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    runs = {r["choices"]["appearance"]: r for r in (json.loads(p.read_text()) for p in sweep.glob("*/results.json"))}
    none, embedding = runs["none"], runs["embedding"]
    assert none["test_protocol"] == "full_image" and none["test_psnr"] == none["test_psnr_full_image"]
    assert embedding["test_protocol"] == "nerfw_right_half"
    assert embedding["test_psnr"] == embedding["test_psnr_right_half"]
    assert embedding["test_psnr_right_half"] > none["test_psnr_right_half"] + 0.4
    report = run_nerfexp(str(sweep), "--reference", "appearance=none", cwd=tmp_path, script="nerfexp-report")
    assert report.returncode == 0, report.stderr[-3000:]
    assert "every test score here is over the right half" in (sweep / "report.md").read_text()


@pytest.mark.slow
def test_a_run_with_codes_and_pose_corrections_killed_and_resumed_ends_as_the_uninterrupted_run(tmp_path):
    # The codes and the pose corrections are sized from the checkpoint before its weights are checked
    # (NeRFModule.on_load_checkpoint), and from the data when training starts; the corrections' parameter group and
    # its schedule are restored with the optimizer: the resumed run is bit-identical, its refined cameras too.
    coded = [*TINY, "appearance=embedding", "appearance.fit.steps=2", "camera_opt=so3xr3",
             "datamodule.pose_noise=[2,0.02]", "test_cameras=refined", "test_cameras.fit.steps=2", "logger=none"]
    alone, killed = tmp_path / "alone", tmp_path / "killed"
    for run_dir, extra in ((alone, []), (killed, kill_at(30))):
        run_dir.mkdir()
        run_nerfexp(*coded, *extra, f"hydra.run.dir={run_dir}", cwd=run_dir, new_process=bool(extra))
    assert final_state(killed)["step"] == 30
    resumed = run_nerfexp(*coded, f"resume={killed}/checkpoints/last.ckpt", f"hydra.run.dir={killed}", cwd=killed)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    state, expected = final_state(killed)["weights"], final_state(alone)["weights"]
    assert expected["renderer.appearance.codes"].shape == (12, 48)  # data.n_train=12 of TINY
    assert state.keys() == expected.keys() and all(torch.equal(state[k], expected[k]) for k in expected)
    assert expected["camera_opt.delta"].shape == (11, 6) and expected["camera_opt.delta"].abs().sum() > 0
    assert read_json(killed / "results.json")["test_psnr"] == read_json(alone / "results.json")["test_psnr"]
    assert read_json(killed / REFINED_POSES)["c2w"] == read_json(alone / REFINED_POSES)["c2w"]


def test_a_runs_test_time_fits_each_say_their_start_in_its_log(tmp_path):
    # a fit of many steps (appearance.fit.steps=1000000000) takes its time after training: its line says why
    fits = ["appearance=embedding", "appearance.fit.steps=3", "appearance.fit.rays=8", "test_cameras=refined",
            "test_cameras.fit.steps=2", "test_cameras.fit.rays=8", "logger=none", "scale.steps=2",
            "scale.val_every=2"]
    result = run_nerfexp(*TINY, *fits, f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    log = (tmp_path / "nerfexp.log").read_text()
    for view in range(2):  # data.n_test=2 of TINY
        assert f"test view {view}: fitting its camera (2 Adam steps of 8 rays)" in log
        assert f"test view {view}: fitting its appearance code (3 Adam steps of 8 rays)" in log
