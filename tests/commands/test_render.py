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

from nerfexp import manifest
from nerfexp.commands import render
from nerfexp.data.procedural import CAMERA_RADIUS
from nerfexp.data.video import FPS_RANGE
from nerfexp.errors import NerfexpError
from nerfexp.geometry.cameras import camera_rays
from nerfexp.geometry.lenses import Intrinsics, distortion_vector
from nerfexp.pixels import to_uint8
from nerfexp.products import frames
from nerfexp.products.camera_files import CameraPath, read_camera_path
from nerfexp.products.frames import (
    default_path,
    frame_images,
    frame_size,
    render_frame,
    render_path,
    scene_focus_depth,
)
from nerfexp.products.trained import load_module
from nerfexp.reading import RECORD_BYTES
from nerfexp.rundir.trained import run_config
from tests.helpers import TINY, cameras_at, digests, run_nerfexp


def test_path_defaults_focus_and_frame_size():
    assert default_path(OmegaConf.create({"_target_": "nerfexp.data.procedural.ProceduralScene"})) == "orbit"
    assert default_path(OmegaConf.create({"_target_": "nerfexp.data.llff.LLFFScene", "ndc": True})) == "spiral"
    assert default_path(OmegaConf.create({"_target_": "some.Scene", "ndc": True})) == "spiral"
    assert default_path(OmegaConf.create({})) == "orbit"
    # (height, width, (fx, fy, cx, cy)) of centred pinholes: focal lengths scale with the width (the field of
    # view across it kept), the principal point stays at the centre of the rounded frame
    assert sized(24, 24, 30.0, 32) == (32, 32, [40.0, 40.0, 16.0, 16.0])
    assert sized(60, 100, 50.0, 50) == (30, 50, [25.0, 25.0, 25.0, 15.0])
    assert sized(61, 100, 50.0, 10) == (6, 10, [5.0, 5.0, 5.0, 3.0])  # 6.1 rounded to an even height
    assert sized(20, 25, 50.0, None) == (20, 24, [48.0, 48.0, 12.0, 10.0])  # the width made even; 19.2 rounded
    # an off-centre, distorted lens: fx, fy, cx times 50 / 100, cy times 30 / 60; the distortion is the lens's
    lens = Intrinsics(torch.tensor([50.0, 55.0, 40.0, 20.0], dtype=torch.float64),
                      distortion_vector({"k1": 0.1, "p1": 0.01}), torch.tensor(False))
    height, width, scaled = frame_size(60, 100, lens, 50)
    assert (height, width, scaled.params.tolist()) == (30, 50, [25.0, 27.5, 20.0, 10.0])
    assert torch.equal(scaled.distortion, lens.distortion) and not scaled.fisheye


def sized(height: int, width: int, focal: float, size: int | None) -> tuple[int, int, list[float]]:
    """``frame_size`` of a centred pinhole of ``focal`` pixels, its lens as ``[fx, fy, cx, cy]``."""
    new_height, new_width, lens = frame_size(height, width, Intrinsics.pinhole(focal, height, width), size)
    assert not lens.is_distorted()
    return new_height, new_width, lens.params.tolist()


def test_chunked_rendering_gives_the_image_of_unchunked_rendering():
    with initialize_config_module("nerfexp.conf", version_base=None):
        cfg = compose("config", overrides=TINY)
    torch.manual_seed(0)
    module, scene = instantiate(cfg.model).eval(), instantiate(cfg.data)
    camera = cameras_at([4.0], [30.0], [20.0])[0]
    module.chunk = 20 * 18
    lens = Intrinsics.pinhole(25.0, 18, 20)
    whole = render_frame(module, scene, camera, 18, 20, lens)
    module.chunk = 7  # 360 rays in 52 chunks, the last one of 3 rays
    chunked = render_frame(module, scene, camera, 18, 20, lens)
    assert whole["rgb"].shape == (18, 20, 3) and whole["depth"].shape == whole["opacity"].shape == (18, 20)
    assert whole["rgb"].std() > 0  # an untrained field, but not a blank image
    for key in whole:
        torch.testing.assert_close(chunked[key], whole[key], atol=1e-6, rtol=1e-6)  # float32 round-off


def read_video(path: Path) -> np.ndarray:
    with imageio.get_reader(path, format="FFMPEG") as reader:
        return np.stack([frame for frame in reader.iter_data()])


def direct_render(module: torch.nn.Module, c2w: list, size: int, lens: Intrinsics) -> dict[str, np.ndarray]:
    """8-bit images of one camera rendered by the run's module in one call: the truth for the frames."""
    origins, directions = camera_rays(torch.tensor(c2w, dtype=torch.float32), size, size, lens)
    out = module.eval().render_image(origins, directions)  # world rays: the procedural scene has no NDC
    near, far = module.renderer.near, module.renderer.far
    depth = ((far - out["depth"]) / (far - near)).clamp(0, 1) * out["opacity"].clamp(0, 1)
    images = {"rgb": out["rgb"], "depth": depth, "opacity": out["opacity"]}
    return {k: torch.round(v.clamp(0, 1) * 255).to(torch.uint8).numpy() for k, v in images.items()}


@pytest.mark.slow
def test_an_orbit_of_a_trained_run_gives_videos_and_frames_of_its_renders(tiny_run, tmp_path):
    result = run_nerfexp(str(tiny_run), "--frames", "6", "--size", "32", cwd=tmp_path, script="nerfexp-render",
                         new_process=True)
    assert result.returncode == 0, result.stderr[-3000:]
    out = tiny_run / "render"
    cameras = json.loads((out / "cameras.json").read_text())
    assert (cameras["path"], cameras["height"], cameras["width"], len(cameras["c2w"])) == ("orbit", 32, 32, 6)
    # the built-in scene's camera: a pinhole centred on the frame, one focal length
    assert (cameras["camera_model"], cameras["cx"], cameras["cy"]) == ("PINHOLE", 16.0, 16.0)
    assert cameras["fl_x"] == cameras["fl_y"] and "focal" not in cameras
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
        truth = direct_render(module, cameras["c2w"][i], 32, Intrinsics.pinhole(cameras["fl_x"], 32, 32))
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


PINHOLE_LENS = {"camera_model": "PINHOLE", "fl_x": 20.0, "fl_y": 20.0, "cx": 10.0, "cy": 8.0}  # 20 x 16 frames
# OpenCV's model with barrel distortion, fx != fy and the principal point off the centre, as lens_record writes it
DISTORTED_LENS = {"camera_model": "OPENCV", "fl_x": 20.0, "fl_y": 21.0, "cx": 11.5, "cy": 7.5, "k1": -0.05,
                  "k2": 0.01, "k3": 0.0, "p1": 0.002, "p2": -0.001}
LEGACY = dict.fromkeys(PINHOLE_LENS)  # no lens keys: a file of an earlier nerfexp, with one ``focal`` instead


def camera_file(path: Path, **changes) -> Path:
    """A cameras file as nerfexp-render and nerfexp-view write them (3 cameras around the origin, a centred
    pinhole), with ``changes`` (a key set to None is left out)."""
    record = {"path": "viewer", "fps": 10, "height": 16, "width": 20, **PINHOLE_LENS,
              "c2w": cameras_at([4.0, 4.0, 4.0], [30.0, 20.0, 10.0], [0.0, 40.0, 80.0]).tolist(), **changes}
    path.write_text(json.dumps({k: v for k, v in record.items() if v is not None}))
    return path


@pytest.mark.parametrize("changes, message", [
    ({"height": None}, "no key 'height': expected a positive even number of pixels"),
    ({"width": 0}, "key 'width': expected a positive even number of pixels, got 0"),
    ({"width": 21}, "key 'width': expected a positive even number of pixels, got 21"),
    ({**LEGACY, "focal": -1}, "key 'focal': expected a focal length in pixels in [2^-24, 2^24], got -1"),
    # issue 39 section 4: extreme values, each where it stops meaning anything (camera_files, cameras.POSITION_LIMIT)
    ({**LEGACY, "focal": 5e-324}, "key 'focal': expected a focal length in pixels in [2^-24, 2^24], got 5e-324"),
    ({**LEGACY, "focal": 1e308}, "key 'focal': expected a focal length in pixels in [2^-24, 2^24], got 1e+308"),
    # the lens keys (nerfexp.geometry.lens_records): focal lengths in [2^-24, 2^24], the principal point within
    # 2^24 of the origin, a model nerfexp writes and only its coefficients
    ({"fl_x": -1}, "key 'fl_x': expected a number of pixels in [5.96e-08, 1.68e+07], got -1"),
    ({"fl_y": 1e308}, "key 'fl_y': expected a number of pixels in [5.96e-08, 1.68e+07], got 1e+308"),
    ({"cx": True}, "key 'cx': expected a number of pixels in [-1.68e+07, 1.68e+07], got True"),
    ({"cy": None}, "key 'cy': missing: expected a number of pixels"),
    ({"camera_model": "SIMPLE_RADIAL"}, "key 'camera_model': expected one of PINHOLE, OPENCV, FULL_OPENCV, "
                                        "OPENCV_FISHEYE, got 'SIMPLE_RADIAL'"),
    ({"k1": 0.1}, "key 'k1': camera_model PINHOLE has no coefficient k1 (it has none), got 0.1"),
    ({**DISTORTED_LENS, "k4": 0.1}, "key 'k4': camera_model OPENCV has no coefficient k4 (it has k1, k2, k3, p1, "
                                    "p2), got 0.1"),
    ({**DISTORTED_LENS, "k1": 1e7}, "key 'k1': expected a finite number within +-1e+06, got 10000000.0"),
    ({**DISTORTED_LENS, "k1": -2.0}, "the lens of 20 x 16 frames: its distortion (k1=-2, k2=0.01, p1=0.002, "
                                     "p2=-0.001) folds the image over itself"),
    ({"fps": 5e-324}, "key 'fps': expected a number of frames per second in [0.001, 1000], got 5e-324"),
    ({"fps": 1e308}, "key 'fps': expected a number of frames per second in [0.001, 1000], got 1e+308"),
    ({"fps": True}, "key 'fps': expected a number of frames per second in [0.001, 1000], got True"),
    ({"c2w": [[[1, 0, 0, 1e308], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]]},
     "item 0 is not a rigid camera pose: its position [1e+308, 0.0, 0.0] is more than 2^24 scene units from the "
     "origin, where float32 positions have no sub-unit resolution"),
    # 2^80 x 20 pixels of 20 bytes: 2^88.6 bytes, said as a power of two (no float overflows on the way)
    ({"height": 2 ** 80}, "a frame of 1208925819614629174706176 x 20 pixels needs about 2^88 bytes of memory"),
    ({"c2w": []}, "key 'c2w': expected a non-empty list of 4 x 4 rigid camera-to-world matrices (OpenGL "
                  "convention), got an empty list"),
    ({"c2w": [[[1, 0, 0, 0]] * 3]}, "key 'c2w': expected a non-empty list of 4 x 4 rigid camera-to-world matrices "
                                    "(OpenGL convention), item 0 is not a 4 x 4 matrix of numbers"),
    ({"c2w": [torch.diag(torch.tensor([2.0, 2, 2, 1])).tolist()]},
     "item 0 is not a rigid camera pose: its rotation is not orthonormal"),
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
    (tmp_path / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
    (tmp_path / "huge.json").write_bytes(b" " * (RECORD_BYTES + 1))
    for name, message in (("bad.json", "not JSON (column 2: Expecting property name"),
                          ("list.json", "expected a JSON object"), ("deep.json", "JSON nested too deeply to read"),
                          ("huge.json", f"larger than the {RECORD_BYTES:,} bytes nerfexp reads of such a file")):
        with pytest.raises(NerfexpError, match=re.escape(f"--cameras {tmp_path / name}: {message}")):
            read_camera_path(tmp_path / name)
    # on the command line: one line, before the run is looked for (there is none here)
    result = run_nerfexp(str(tmp_path / "no_run"), "--cameras", str(tmp_path / "bad.json"), cwd=tmp_path,
                         script="nerfexp-render")
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 1 and len(lines) == 1, result.stderr[-2000:]
    assert lines[0].startswith(f"nerfexp-render: error: --cameras {tmp_path / 'bad.json'}: not JSON"), lines


def lens_of(record: dict) -> Intrinsics:
    """The lens of a camera file's keys, read here from nerfstudio's names (not by nerfexp's reader)."""
    params = torch.tensor([record[key] for key in ("fl_x", "fl_y", "cx", "cy")], dtype=torch.float64)
    coefficients = {name: value for name, value in record.items() if name in ("k1", "k2", "k3", "p1", "p2")}
    return Intrinsics(params, distortion_vector(coefficients), torch.tensor(False))


LENSES = {  # one of each model a cameras file holds, each with its principal point off the centre
    "OPENCV": Intrinsics(torch.tensor([20.0, 21.0, 11.5, 7.5], dtype=torch.float64),
                         distortion_vector({"k1": -0.05, "k2": 0.01, "p1": 0.002, "p2": -0.001}), torch.tensor(False)),
    "FULL_OPENCV": Intrinsics(torch.tensor([20.0, 20.0, 9.25, 8.5], dtype=torch.float64),
                              distortion_vector({"k1": 0.1, "k4": 0.05, "k5": 0.01, "p2": 0.003}), torch.tensor(False)),
    "OPENCV_FISHEYE": Intrinsics(torch.tensor([12.0, 12.0, 10.5, 8.0], dtype=torch.float64),
                                 distortion_vector({"k1": 0.02, "k2": -0.003}), torch.tensor(True)),
}


@pytest.mark.parametrize("model", LENSES)
def test_a_distorted_lens_round_trips_through_a_cameras_file_exactly(tmp_path, model):
    lens = LENSES[model]
    cameras = CameraPath("spiral", cameras_at([4.0, 3.5], [30.0, 25.0], [0.0, 40.0]), 16, 20, lens, 12.5)
    record = cameras.record()
    assert record["camera_model"] == model and "focal" not in record
    assert [record[key] for key in ("fl_x", "fl_y", "cx", "cy")] == lens.params.tolist()
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps(record))
    read = read_camera_path(path)
    assert (read.name, read.height, read.width, read.fps) == ("spiral", 16, 20, 12.5)
    assert torch.equal(read.c2w, cameras.c2w)  # float64 written as JSON's shortest repr: exact
    assert torch.equal(read.intrinsics.params, lens.params) and torch.equal(read.intrinsics.distortion, lens.distortion)
    assert read.intrinsics.fisheye.item() == lens.fisheye.item() and read.intrinsics.shape == ()
    assert read.record() == record


def test_a_cameras_file_of_an_earlier_nerfexp_is_a_pinhole_centred_on_its_frames(tmp_path):
    read = read_camera_path(camera_file(tmp_path / "cameras.json", **LEGACY, focal=20.0))
    assert read.intrinsics.params.tolist() == [20.0, 20.0, 10.0, 8.0] and not read.intrinsics.is_distorted()
    assert {key: read.record()[key] for key in PINHOLE_LENS} == PINHOLE_LENS


def test_a_bad_lens_key_is_one_line_naming_the_key_before_the_run_is_read(tmp_path):
    path = camera_file(tmp_path / "cameras.json", **{**DISTORTED_LENS, "fl_x": 0})
    result = run_nerfexp(str(tmp_path / "no_run"), "--cameras", str(path), cwd=tmp_path, script="nerfexp-render")
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 1 and lines == [
        f"nerfexp-render: error: --cameras {path}: key 'fl_x': expected a number of pixels in [5.96e-08, 1.68e+07], "
        "got 0"], result.stderr[-2000:]


@pytest.mark.slow
def test_rendering_a_cameras_file_renders_exactly_its_cameras(tiny_run, tmp_path):
    path = camera_file(tmp_path / "camera_path.json", **DISTORTED_LENS)
    result = run_nerfexp(str(tiny_run), "--cameras", str(path), cwd=tmp_path, script="nerfexp-render")
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.strip().endswith(f"3 frames written to {tiny_run / 'render'}")
    out = tiny_run / "render"
    written = json.loads((out / "cameras.json").read_text())
    assert written == json.loads(path.read_text())  # the file's cameras, size, lens and fps
    lens = lens_of(DISTORTED_LENS)
    module, _ = load_module(run_config(tiny_run), tiny_run / "checkpoints" / "last.ckpt")
    scene = instantiate(run_config(tiny_run).data)
    near, far = module.renderer.near, module.renderer.far
    # Within one level of 255 of this process's render, not bit for bit: the float matrix products of two
    # processes may differ in their last bits (the BLAS may pick its kernels by the buffers' alignment), and a
    # value that close to a rounding boundary lands one level apart (seen once in CI, in 'rgb' of frame 0).
    # The frames differ from one another by far more, so a frame of another camera would not pass.
    for i, c2w in enumerate(written["c2w"]):
        truth = frame_images(render_frame(module.eval(), scene, torch.tensor(c2w), 16, 20, lens), near, far)
        for kind, image in truth.items():
            written_pixels = imageio.imread(out / kind / f"{i:04d}.png").astype(int)
            assert np.abs(written_pixels - to_uint8(image)).max() <= 1, (i, kind)
    frames = [imageio.imread(out / "rgb" / f"{i:04d}.png").astype(int) for i in range(3)]
    assert min(np.abs(frames[i] - frames[j]).max() for i, j in ((0, 1), (1, 2), (0, 2))) > 10

    # --size rescales the file's frames, keeping the field of view; path options do not apply
    result = run_nerfexp(str(tiny_run), "--cameras", str(path), "--size", "10", cwd=tmp_path, script="nerfexp-render")
    assert result.returncode == 0, result.stderr[-3000:]
    written = json.loads((out / "cameras.json").read_text())
    # 20 x 16 to 10 x 8: focal lengths and principal point halved, the distortion the file's
    assert (written["height"], written["width"]) == (8, 10)
    assert written == {**json.loads(path.read_text()), "height": 8, "width": 10, "fl_x": 10.0, "fl_y": 10.5,
                       "cx": 5.75, "cy": 3.75}
    assert imageio.imread(out / "rgb" / "0002.png").shape == (8, 10, 3)
    result = run_nerfexp(str(tiny_run), "--cameras", str(path), "--frames", "5", cwd=tmp_path,
                         script="nerfexp-render")
    assert result.returncode == 2 and "--cameras renders the file's cameras: --frames do not apply" in result.stderr


def test_a_render_replaces_its_own_folder_and_refuses_one_holding_a_users_file(tiny_run, tmp_path):
    run_dir = shutil.copytree(tiny_run, tmp_path / "run", ignore=shutil.ignore_patterns("render"))
    render.main([str(run_dir), "--frames", "3", "--size", "8"])
    render.main([str(run_dir), "--frames", "2", "--size", "8"])  # its own folder: replaced as a whole
    assert sorted(p.name for p in (run_dir / "render" / "rgb").iterdir()) == ["0000.png", "0001.png"]
    assert manifest.unproven(run_dir, manifest.folder_files(run_dir, "render")) == []
    assert not [entry for entry in manifest.read_records(run_dir) if entry.startswith("render/rgb/0002")]

    (run_dir / "render" / "notes.txt").write_text("mine")  # a user's file beside a render's, and one in its place
    (run_dir / "render" / "rgb" / "0001.png").write_bytes(b"a user's own frame")
    before = digests(run_dir / "render")
    with pytest.raises(SystemExit) as exit:
        render.main([str(run_dir), "--frames", "2", "--size", "8"])
    assert exit.value.code == (
        f"nerfexp-render: error: {run_dir / 'render/notes.txt'}, {run_dir / 'render/rgb/0001.png'} are not files "
        f"nerfexp-render wrote (they are not in {run_dir / manifest.MANIFEST}, or changed since): move them "
        "elsewhere: nerfexp-render replaces this folder as a whole")
    assert digests(run_dir / "render") == before and not list(run_dir.glob(".render*"))


@pytest.mark.parametrize(("arguments", "message"), [
    (["--fps", "1e308"], "argument --fps: expected a number in [0.001, 1000], got 1e308"),
    (["--fps", "5e-324"], "argument --fps: expected a number in [0.001, 1000], got 5e-324"),
    (["--fps", "nan"], "argument --fps: expected a number in [0.001, 1000], got nan"),
    (["--focus", "1e308"], "argument --focus: expected a finite number > 0 and <= 2^24, got 1e308"),
    (["--frames", str(2 ** 70)], f"argument --frames: {2 ** 70}: a camera path of {2 ** 70} frames needs about 2^77 "
                                 "bytes of memory, more than this machine's "),
    (["--size", str(10 ** 400)], "argument --size: " + "1" + "0" * 400 + ": a frame of "),
])
def test_an_argument_beyond_what_it_can_mean_is_one_line_before_the_run_is_read(tmp_path, capsys, arguments,
                                                                                message):
    # issue 39 section 4: "--fps 1e308" printed "2 frames written" with no video; a camera 1e308 away was black
    with pytest.raises(SystemExit) as exit:
        render.main([str(tmp_path / "no_run"), *arguments])
    assert exit.value.code == 2 and capsys.readouterr().err.splitlines()[-1].startswith(
        f"nerfexp-render: error: {message}")


@pytest.mark.parametrize("fps", FPS_RANGE)
def test_videos_are_written_at_either_end_of_the_frame_rates_nerfexp_takes(tiny_run, tmp_path, fps):
    module, _ = load_module(run_config(tiny_run), tiny_run / "checkpoints" / "last.ckpt")
    scene = instantiate(run_config(tiny_run).data)
    render_path(module, scene, cameras_at([4.0, 4.0], [30.0, 20.0], [0.0, 40.0]), 8, 8, Intrinsics.pinhole(10.0, 8, 8),
                tmp_path, fps)
    for kind in ("rgb", "depth", "opacity"):
        with imageio.get_reader(tmp_path / f"{kind}.mp4") as video:
            assert video.count_frames() == 2


def test_a_video_ffmpeg_did_not_write_is_an_error_not_a_frame_count(tiny_run, tmp_path, monkeypatch):
    # imageio's writer leaves ffmpeg's failure to ffmpeg's stderr: the files are checked
    class Silent:
        def __init__(self, *args, **kwargs):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def append_data(self, frame):
            pass

    monkeypatch.setattr(frames.imageio, "get_writer", Silent)
    module, _ = load_module(run_config(tiny_run), tiny_run / "checkpoints" / "last.ckpt")
    scene = instantiate(run_config(tiny_run).data)
    with pytest.raises(NerfexpError, match=r"^ffmpeg wrote no rgb.mp4, depth.mp4, opacity.mp4 at 30 frames per "
                                           r"second \(its messages above say why\)$"):
        render_path(module, scene, cameras_at([4.0], [30.0], [0.0]), 8, 8, Intrinsics.pinhole(10.0, 8, 8), tmp_path,
                    30.0)


def test_a_camera_as_far_as_cameras_may_be_renders_finite_images(tiny_run):
    # float32 positions 2^24 from the origin are a unit apart: still rays, still finite colours (not NaN's black)
    module, _ = load_module(run_config(tiny_run), tiny_run / "checkpoints" / "last.ckpt")
    scene = instantiate(run_config(tiny_run).data)
    frame = render_frame(module, scene, cameras_at([2.0 ** 24 * 0.99], [30.0], [0.0])[0], 4, 4,
                         Intrinsics.pinhole(5.0, 4, 4))
    assert all(torch.isfinite(image).all() for image in frame.values())
    assert ((frame["rgb"] >= 0) & (frame["rgb"] <= 1)).all()
