"""``nerfexp-render``: camera paths against hand-worked geometry, chunked rendering against unchunked,
and the command line on a trained run against direct renders of the same cameras."""

import json
import re
import shutil
from pathlib import Path
from types import SimpleNamespace

import imageio.v2 as imageio
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate
from omegaconf import OmegaConf

from nerfexp.commands import render
from nerfexp.data.procedural import CAMERA_RADIUS
from nerfexp.errors import NerfexpError
from nerfexp.geometry.cameras import camera_rays
from nerfexp.pixels import to_uint8
from nerfexp.products.camera_files import read_camera_path
from nerfexp.products.frames import default_path, frame_images, frame_size, render_frame, scene_focus_depth
from nerfexp.rundir.trained import load_module, run_config
from tests.helpers import TINY, cameras_at, run_nerfexp


def test_path_defaults_focus_and_frame_size():
    assert default_path(OmegaConf.create({"_target_": "nerfexp.data.procedural.ProceduralScene"})) == "orbit"
    assert default_path(OmegaConf.create({"_target_": "nerfexp.data.llff.LLFFScene", "ndc": True})) == "spiral"
    assert default_path(OmegaConf.create({"_target_": "some.Scene", "ndc": True})) == "spiral"
    assert default_path(OmegaConf.create({})) == "orbit"
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
        torch.testing.assert_close(chunked[key], whole[key], atol=1e-6, rtol=1e-6)  # float32 round-off


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


def test_the_spirals_focus_depth_comes_from_the_views_depth_bounds_else_the_ray_bounds():
    # LLFF records per-view depth bounds (2 to 6 over its views); other scenes give their ray bounds
    # (near 2, far 6): 1 / (0.25 / 1.8 + 0.75 / 30) either way
    expected = 1 / (0.25 / 1.8 + 0.75 / 30)
    per_view = SimpleNamespace(depth_bounds=lambda: torch.tensor([[2.0, 5.0], [3.0, 6.0]]), ray_bounds=None)
    ray_bounds_only = SimpleNamespace(depth_bounds=lambda: None, ray_bounds=lambda: (2.0, 6.0))
    for scene in (per_view, ray_bounds_only):
        assert scene_focus_depth(scene) == pytest.approx(expected)


def camera_file(path: Path, **changes) -> Path:
    """A cameras file as nerfexp-render and nerfexp-view write them (3 cameras around the origin), with ``changes``."""
    record = {"path": "viewer", "fps": 10, "height": 16, "width": 20, "focal": 20.0,
              "c2w": cameras_at([4.0, 4.0, 4.0], [30.0, 20.0, 10.0], [0.0, 40.0, 80.0]).tolist(), **changes}
    path.write_text(json.dumps({k: v for k, v in record.items() if v is not None}))
    return path


@pytest.mark.parametrize("changes, message", [
    ({"height": None}, "no key 'height': expected a positive even number of pixels"),
    ({"width": 0}, "key 'width': expected a positive even number of pixels, got 0"),
    ({"width": 21}, "key 'width': expected a positive even number of pixels, got 21"),
    ({"focal": -1}, "key 'focal': expected a positive focal length in pixels, got -1"),
    ({"c2w": []}, "key 'c2w': expected a non-empty list of 4 x 4 rigid camera-to-world matrices (OpenGL "
                  "convention), got an empty list"),
    ({"c2w": [[[1, 0, 0, 0]] * 3]}, "key 'c2w': expected a non-empty list of 4 x 4 rigid camera-to-world matrices "
                                    "(OpenGL convention), item 0 is not a 4 x 4 matrix of numbers"),
    ({"c2w": [torch.diag(torch.tensor([2.0, 2, 2, 1])).tolist()]},
     "item 0 is not a rigid transform: its rotation is not orthonormal"),
    ({"c2w": "cameras"}, "got a str"),
])
def test_a_bad_cameras_file_is_one_error_naming_the_file_the_key_and_what_was_expected(tmp_path, changes, message):
    path = camera_file(tmp_path / "cameras.json", **changes)
    with pytest.raises(NerfexpError) as error:
        read_camera_path(path)
    assert str(error.value).startswith(f"--cameras {path}: ") and message in str(error.value)


def test_a_cameras_file_that_is_no_json_object_is_refused_before_the_run_is_read(tmp_path):
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "list.json").write_text("[1, 2]")
    for name, message in (("bad.json", "not JSON (Expecting property name"), ("list.json", "expected a JSON object")):
        with pytest.raises(NerfexpError, match=re.escape(f"--cameras {tmp_path / name}: {message}")):
            read_camera_path(tmp_path / name)
    # on the command line: one line, before the run is looked for (there is none here)
    result = run_nerfexp(str(tmp_path / "no_run"), "--cameras", str(tmp_path / "bad.json"), cwd=tmp_path,
                         script="nerfexp-render")
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 1 and len(lines) == 1, result.stderr[-2000:]
    assert lines[0].startswith(f"nerfexp-render: error: --cameras {tmp_path / 'bad.json'}: not JSON"), lines


@pytest.mark.slow
def test_rendering_a_cameras_file_renders_exactly_its_cameras(tiny_run, tmp_path):
    path = camera_file(tmp_path / "camera_path.json")
    result = run_nerfexp(str(tiny_run), "--cameras", str(path), cwd=tmp_path, script="nerfexp-render")
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.strip().endswith(f"3 frames written to {tiny_run / 'render'}")
    out = tiny_run / "render"
    written = json.loads((out / "cameras.json").read_text())
    assert written == json.loads(path.read_text())  # the file's cameras, size, focal length and fps
    module, _ = load_module(run_config(tiny_run), tiny_run / "checkpoints" / "last.ckpt")
    scene = instantiate(run_config(tiny_run).data)
    near, far = module.renderer.near, module.renderer.far
    # Within one level of 255 of this process's render, not bit for bit: the float matrix products of two
    # processes may differ in their last bits (the BLAS may pick its kernels by the buffers' alignment), and a
    # value that close to a rounding boundary lands one level apart (seen once in CI, in 'rgb' of frame 0).
    # The frames differ from one another by far more, so a frame of another camera would not pass.
    for i, c2w in enumerate(written["c2w"]):
        truth = frame_images(render_frame(module.eval(), scene, torch.tensor(c2w), 16, 20, 20.0), near, far)
        for kind, image in truth.items():
            written_pixels = imageio.imread(out / kind / f"{i:04d}.png").astype(int)
            assert np.abs(written_pixels - to_uint8(image)).max() <= 1, (i, kind)
    frames = [imageio.imread(out / "rgb" / f"{i:04d}.png").astype(int) for i in range(3)]
    assert min(np.abs(frames[i] - frames[j]).max() for i, j in ((0, 1), (1, 2), (0, 2))) > 10

    # --size rescales the file's frames, keeping the field of view; path options do not apply
    result = run_nerfexp(str(tiny_run), "--cameras", str(path), "--size", "10", cwd=tmp_path, script="nerfexp-render")
    assert result.returncode == 0, result.stderr[-3000:]
    written = json.loads((out / "cameras.json").read_text())
    assert (written["height"], written["width"], written["focal"]) == (8, 10, 10.0)
    assert imageio.imread(out / "rgb" / "0002.png").shape == (8, 10, 3)
    result = run_nerfexp(str(tiny_run), "--cameras", str(path), "--frames", "5", cwd=tmp_path,
                         script="nerfexp-render")
    assert result.returncode == 2 and "--cameras renders the file's cameras: --frames do not apply" in result.stderr


def test_a_render_folder_holding_a_users_file_is_refused_and_the_file_kept(tiny_run, tmp_path):
    run_dir = shutil.copytree(tiny_run, tmp_path / "run")
    (run_dir / "render").mkdir(exist_ok=True)
    (run_dir / "render" / "notes.txt").write_text("mine")
    with pytest.raises(SystemExit) as exit:
        render.main([str(run_dir), "--frames", "2", "--size", "8"])
    assert exit.value.code == (f"nerfexp-render: error: {run_dir / 'render'} holds files nerfexp-render did not "
                               "make (notes.txt): move them elsewhere: nerfexp-render replaces this folder as a whole")
    assert (run_dir / "render" / "notes.txt").read_text() == "mine" and not list(run_dir.glob(".render*"))
