"""``nerfexp-render``: camera paths against hand-worked geometry, chunked rendering against unchunked,
and the command line on a trained run against direct renders of the same cameras."""

import json
import math
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate
from omegaconf import OmegaConf

from conftest import TINY, run_nerfexp
from nerfexp.cameras import camera_rays, look_at
from nerfexp.data.procedural import CAMERA_RADIUS
from nerfexp.outputs import load_module, run_config
from nerfexp.render import default_path, frame_size, llff_focus_depth, orbit_path, render_frame, spiral_path

Z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)


def cameras_at(distance: list[float], elevation_deg: list[float], azimuth_deg: list[float]) -> torch.Tensor:
    """Cameras [N, 4, 4] at the given spherical coordinates (z up), looking at the origin."""
    r, e, a = (torch.tensor(v, dtype=torch.float64) for v in (distance, elevation_deg, azimuth_deg))
    e, a = torch.deg2rad(e), torch.deg2rad(a)
    eye = r[:, None] * torch.stack([e.cos() * a.cos(), e.cos() * a.sin(), e.sin()], -1)
    return look_at(eye, torch.zeros(3, dtype=torch.float64), Z)


def test_an_orbit_circles_at_the_cameras_mean_distance_and_elevation():
    # Distances 3, 5.5, 3, 4.5 (mean 4), elevations 30 and 50 degrees (mean 40), opposite azimuths in
    # pairs of equal elevation (so the mean up is exactly z): the orbit is the circle of radius
    # 4 cos 40deg = 3.064 at height 4 sin 40deg = 2.571.
    cams = cameras_at([3, 5.5, 3, 4.5], [30, 50, 30, 50], [10, 100, 190, 280])
    orbit = orbit_path(cams, 8)
    eyes = orbit[:, :3, 3]
    assert orbit.shape == (8, 4, 4)
    torch.testing.assert_close(eyes[:, 2], torch.full((8,), 4 * math.sin(math.radians(40)), dtype=torch.float64))
    torch.testing.assert_close(eyes[:, :2].norm(dim=-1), torch.full((8,), 4 * math.cos(math.radians(40)),
                                                                     dtype=torch.float64))
    # each camera looks at the origin (its back axis points from the origin to it), z up on screen
    torch.testing.assert_close(orbit[:, :3, 2], eyes / eyes.norm(dim=-1, keepdim=True))
    assert (orbit[:, 2, 1] > 0).all()
    # evenly spaced, 45 degrees apart, counterclockwise about z, starting at the azimuth of the camera
    # farthest from the axis: 100 degrees (5.5 cos 50deg = 3.54 from it; the others 2.89 and 2.60)
    azimuth = torch.deg2rad(100 + 45 * torch.arange(8, dtype=torch.float64))
    ring = torch.stack([azimuth.cos(), azimuth.sin()], -1)
    torch.testing.assert_close(eyes[:, :2], 4 * math.cos(math.radians(40)) * ring)


def test_a_spiral_looks_at_its_focus_point_in_front_of_the_mean_camera():
    # Five forward-facing cameras near z = 0, all looking down -z: the mean camera is at the origin.
    offsets = torch.tensor([[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 0.5, 0.2], [0, -0.5, -0.2]], dtype=torch.float64)
    cams = torch.eye(4, dtype=torch.float64).repeat(5, 1, 1)
    cams[:, :3, 3] = offsets
    spiral = spiral_path(cams, 16, focus_depth=10.0)
    eyes, focus = spiral[:, :3, 3], torch.tensor([0, 0, -10.0], dtype=torch.float64)
    torch.testing.assert_close(spiral[:, :3, 2], (eyes - focus) / (eyes - focus).norm(dim=-1, keepdim=True))
    # radii: 90th percentiles of |offsets| per axis, (1, 0.5, 0.2); two turns in 16 frames, so frame 2 is a
    # quarter turn: frame 0 at (r_x, 0, 0), frame 2 at (0, -r_y, -r_z sin(pi/4))
    torch.testing.assert_close(eyes[0], torch.tensor([1.0, 0, 0], dtype=torch.float64))
    torch.testing.assert_close(eyes[2], torch.tensor([0, -0.5, -0.2 * math.sin(math.pi / 4)], dtype=torch.float64))
    assert (spiral[:, 1, 1] > 0.9).all()  # upright


def test_path_defaults_focus_and_frame_size():
    assert default_path(OmegaConf.create({"_target_": "nerfexp.data.procedural.ProceduralScene"})) == "orbit"
    assert default_path(OmegaConf.create({"_target_": "nerfexp.data.llff.LLFFScene", "ndc": True})) == "spiral"
    assert default_path(OmegaConf.create({"_target_": "some.Scene", "ndc": True})) == "spiral"
    assert default_path(OmegaConf.create({})) == "orbit"
    assert llff_focus_depth(2.0, 6.0) == pytest.approx(1 / (0.25 / 1.8 + 0.75 / 30))  # 6.08
    assert frame_size(24, 24, 30.0, 32) == (32, 32, 40.0)
    assert frame_size(60, 100, 50.0, 50) == (30, 50, 25.0)
    assert frame_size(61, 100, 50.0, 10) == (6, 10, 5.0)  # 6.1 rounded to an even height
    assert frame_size(20, 25, 50.0, None) == (20, 24, 48.0)  # the views' width made even; 19.2 rounded


def test_chunked_rendering_gives_the_image_of_unchunked_rendering():
    with initialize_config_module("nerfexp.conf", version_base=None):
        cfg = compose("config", overrides=TINY)
    torch.manual_seed(0)
    module, scene = instantiate(cfg.model).eval(), instantiate(cfg.data)
    camera = cameras_at([4.0], [30.0], [20.0])[0]
    module.chunk = 20 * 18
    whole = render_frame(module, scene, camera, 18, 20, 25.0)
    module.chunk = 7  # 360 rays in 52 chunks, the last one of 3 rays
    chunked = render_frame(module, scene, camera, 18, 20, 25.0)
    assert whole["rgb"].shape == (18, 20, 3) and whole["depth"].shape == whole["opacity"].shape == (18, 20)
    assert whole["rgb"].std() > 0  # an untrained field, but not a blank image
    for key in whole:
        torch.testing.assert_close(chunked[key], whole[key], atol=1e-6, rtol=0)


def read_video(path: Path) -> np.ndarray:
    with imageio.get_reader(path, format="FFMPEG") as reader:
        return np.stack([frame for frame in reader.iter_data()])


def direct_render(module: torch.nn.Module, c2w: list, size: int, focal: float) -> dict[str, np.ndarray]:
    """8-bit images of one camera rendered by the run's module in one call: the truth for the frames."""
    origins, directions = camera_rays(torch.tensor(c2w, dtype=torch.float32), size, size, focal)
    out = module.eval().render_image(origins, directions)  # world rays: the procedural scene has no NDC
    near, far = module.renderer.near, module.renderer.far
    depth = ((far - out["depth"]) / (far - near)).clamp(0, 1) * out["opacity"].clamp(0, 1)
    images = {"rgb": out["rgb"], "depth": depth, "opacity": out["opacity"]}
    return {k: torch.round(v.clamp(0, 1) * 255).to(torch.uint8).numpy() for k, v in images.items()}


@pytest.mark.slow
def test_an_orbit_of_a_trained_run_gives_videos_and_frames_of_its_renders(tiny_run, tmp_path):
    result = run_nerfexp(str(tiny_run), "--frames", "6", "--size", "32", cwd=tmp_path, script="nerfexp-render")
    assert result.returncode == 0, result.stderr[-3000:]
    out = tiny_run / "render"
    cameras = json.loads((out / "cameras.json").read_text())
    assert (cameras["path"], cameras["height"], cameras["width"], len(cameras["c2w"])) == ("orbit", 32, 32, 6)
    # the built-in scene's training cameras are all CAMERA_RADIUS from the origin: so is the orbit
    eyes = torch.tensor(cameras["c2w"])[:, :3, 3]
    torch.testing.assert_close(eyes.norm(dim=-1), torch.full((6,), CAMERA_RADIUS, dtype=torch.float32))
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["cameras.json", "rgb.mp4", "depth.mp4", "opacity.mp4", "rgb", "depth", "opacity"])

    frames = {kind: np.stack([imageio.imread(out / kind / f"{i:04d}.png") for i in range(6)])
              for kind in ("rgb", "depth", "opacity")}
    for kind, pngs in frames.items():
        assert sorted(p.name for p in (out / kind).iterdir()) == [f"{i:04d}.png" for i in range(6)]
        video = read_video(out / f"{kind}.mp4")
        assert video.shape == (6, 32, 32, 3) and video.dtype == np.uint8
        grey = pngs if pngs.ndim == 4 else pngs[..., None]
        # H.264 is lossy: the video's frames are the PNGs up to compression noise
        assert np.abs(video.astype(int) - grey.astype(int)).mean() < 3, kind
    assert frames["rgb"].shape == (6, 32, 32, 3) and frames["depth"].shape == (6, 32, 32)
    assert all(np.ptp(frame) > 20 for frame in frames["rgb"])  # not a constant image
    assert not np.array_equal(frames["rgb"][0], frames["rgb"][3])  # the camera moved

    # each frame is the module's own render of that camera, to the 8-bit level
    module, _ = load_module(run_config(tiny_run), tiny_run / "checkpoints" / "last.ckpt")
    for i in (0, 4):
        truth = direct_render(module, cameras["c2w"][i], 32, cameras["focal"])
        for kind in frames:
            assert np.array_equal(frames[kind][i], truth[kind]), (i, kind)

    # a checkpoint path works as well as the run directory; other chunks give the same frames
    checkpoint = tiny_run / "checkpoints" / "last.ckpt"
    again = run_nerfexp(str(checkpoint), "--frames", "6", "--size", "32", "--chunk", "37", cwd=tmp_path,
                        script="nerfexp-render")
    assert again.returncode == 0, again.stderr[-3000:]
    for kind, pngs in frames.items():
        rerendered = np.stack([imageio.imread(out / kind / f"{i:04d}.png") for i in range(6)])
        assert np.abs(rerendered.astype(int) - pngs.astype(int)).max() <= 1, kind  # rounding at most
    assert not list(tiny_run.glob(".render*"))  # no temporary folder left behind


@pytest.mark.parametrize("make", ["nothing", "checkpoint_outside_a_run"])
def test_rendering_a_missing_run_is_one_clear_line(tmp_path, make):
    path = tmp_path / "missing"
    if make == "checkpoint_outside_a_run":
        path = tmp_path / "somewhere" / "model.ckpt"
        path.parent.mkdir()
        path.write_bytes(b"")
    result = run_nerfexp(str(path), "--frames", "2", cwd=tmp_path, script="nerfexp-render")
    lines = result.stderr.strip().splitlines()
    expected = str(path) if make == "nothing" else f"{tmp_path} is not a run directory"
    assert result.returncode == 1 and len(lines) == 1, result.stderr[-2000:]
    assert lines[0].startswith("nerfexp-render: error: ") and expected in lines[0], lines


def test_focus_depth_from_a_scene_whose_bounds_are_a_method_or_an_attribute():
    # LLFF keeps per-view bounds as an attribute, COLMAP returns (near, far) from bounds(): near 2, far 6
    # give 1 / (0.25 / 1.8 + 0.75 / 30) either way
    from types import SimpleNamespace

    from nerfexp.render import scene_focus_depth

    expected = 1 / (0.25 / 1.8 + 0.75 / 30)
    as_attribute = SimpleNamespace(bounds=torch.tensor([[2.0, 5.0], [3.0, 6.0]]))
    as_method = SimpleNamespace(bounds=lambda: (2.0, 6.0))
    for scene in (as_attribute, as_method):
        assert scene_focus_depth(scene, OmegaConf.create({})) == pytest.approx(expected)
