"""Every value nerfexp reads from a dataset's or a camera file's JSON has a type and a finite range checked where it
is read, and so has what is derived from it (Instant-NGP's scene box): any value of any type either reads as the
format means it or ends in one line naming the file and the key, never a traceback or a box the grid cannot cover."""

import json
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nerfexp.data.blender import read_transforms
from nerfexp.data.colmap import colmap_lens, load_colmap
from nerfexp.data.llff import read_poses_bounds, write_llff
from nerfexp.data.nerfstudio import NerfstudioScene
from nerfexp.data.procedural import scene_cameras
from nerfexp.data.transforms_file import TRANSFORMS, frame_lens_fields, read_capture
from nerfexp.data.video import cached_frames
from nerfexp.errors import DatasetError, NerfexpError
from nerfexp.geometry.lens_records import LensRecordError, read_lens_record
from nerfexp.geometry.lenses import Intrinsics
from nerfexp.pixels import png_bytes
from nerfexp.products.camera_files import CameraPath, read_camera_path

LIMIT = 2.0 ** 24  # scene units: distances and positions (nerfexp.domains.POSITION_LIMIT)

# values of every JSON type, and the numbers that break arithmetic: NaN, infinities, the tiniest and largest
# floats, whole numbers with no float64
EXTREMES = [math.nan, math.inf, -math.inf, 5e-324, 1e-300, 1e-9, 1e300, -1e300, 10 ** 400, -(10 ** 400), 2 ** 64,
            0, -1, True, None, "1", "", [], {}, [1.0], {"x": 1}]
ANY_VALUE = st.one_of(st.sampled_from(EXTREMES), st.floats(allow_nan=True, allow_infinity=True), st.integers(),
                      st.text(max_size=4), st.lists(st.floats(allow_nan=True), max_size=4), st.booleans(), st.none())


def ngp_file(root: Path, centre: float = 0.0, **keys) -> Path:
    """A transforms file of Instant-NGP's kind (camera_angle_x, aabb_scale) of four of the built-in scene's
    cameras moved by ``centre`` along each axis, with ``keys`` over its own; its images need not exist (the box
    is read from the file alone)."""
    c2w = scene_cameras("train", 4)
    c2w[:, :3, 3] += centre
    frames = [{"file_path": f"images/{i}.png", "transform_matrix": pose.tolist()} for i, pose in enumerate(c2w)]
    content = {"camera_angle_x": 0.69, "aabb_scale": 2, "scale": 0.5, "offset": [0.5, 0.5, 0.5], "frames": frames,
               **keys}
    root.mkdir(parents=True, exist_ok=True)
    (root / TRANSFORMS).write_text(json.dumps(content))
    return root / TRANSFORMS


def one_line_naming(error: Exception, *names: str) -> bool:
    message = str(error)
    return "\n" not in message and all(name in message for name in names)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(key=st.sampled_from(["aabb_scale", "scale", "offset"]), value=ANY_VALUE,
       centre=st.sampled_from([0.0, 1000.0, -3.0e6]))
def test_any_box_key_gives_the_box_it_means_or_one_line_naming_the_file_and_the_key(tmp_path, key, value, centre):
    with tempfile.TemporaryDirectory(dir=tmp_path) as folder:
        keys = {key: [value, 0.5, 0.5] if key == "offset" and not isinstance(value, list) else value}
        path = ngp_file(Path(folder), centre, **keys)
        scene = NerfstudioScene(root=folder)
        try:
            box = scene.bounding_box()
        except DatasetError as error:
            assert one_line_naming(error, str(path)), error
            assert f"'{key}' must be" in str(error) or "the scene box of 'aabb_scale'" in str(error), error
            return
        # read: the box as Instant-NGP means it (float64, by hand), moved and scaled as the poses are, and one
        # an occupancy grid covers (finite, within 2^24, lower corner below the upper in float32)
        side, scale, offset = (keys.get("aabb_scale", 2), keys.get("scale", 0.5), keys.get("offset", [0.5] * 3))
        centre_ngp = torch.tensor([0.5 - offset[2], 0.5 - offset[0], 0.5 - offset[1]], dtype=torch.float64) / scale
        expected = torch.stack([centre_ngp - side / (2 * scale), centre_ngp + side / (2 * scale)])
        mean, factor = scene.posed().centre, scene.posed().scale
        assert torch.allclose(box, ((expected - mean) * factor).float())
        assert torch.isfinite(box).all() and box.abs().max() <= LIMIT and (box[0] < box[1]).all()


@pytest.mark.parametrize(("keys", "centre", "says"), [
    ({"offset": [math.nan, 0.5, 0.5]}, 0.0, "'offset' must be a list of 3 numbers within +-2^24, got [nan, 0.5, 0.5]"),
    ({"scale": 1e-300}, 0.0, "reaches more than 2^24 scene units from the origin"),
    ({"scale": 5e-324}, 0.0, "is not finite"),
    ({"aabb_scale": 1e-9, "scale": 0.33}, 1000.0, "is empty: as float32 its lower corner is not below its upper"),
    ({"aabb_scale": "2"}, 0.0, "'aabb_scale' must be a positive number at most 2^16"),
    ({"offset": [10 ** 400, 0, 0]}, 0.0, "'offset' must be a list of 3 numbers within +-2^24"),
])
def test_a_scene_box_that_is_empty_infinite_or_of_odd_values_is_one_line(tmp_path, keys, centre, says):
    # aabb_scale 1e-9 around the origin of the file: non-empty there, but the cameras lie 1000 units away, and
    # moved and scaled with them it has no volume in float32; scale 1e-300: a half side of 3e300
    path = ngp_file(tmp_path, centre, **keys)
    with pytest.raises(DatasetError) as caught:
        NerfstudioScene(root=str(tmp_path)).bounding_box()
    assert one_line_naming(caught.value, str(path), says), caught.value


@pytest.mark.parametrize(("change", "says"), [
    (lambda c: c.update(camera_model=["OPENCV"]), "'camera_model': expected one of PINHOLE"),
    (lambda c: c.update(camera_model={"name": "PINHOLE"}), "'camera_model': expected one of PINHOLE"),
    (lambda c: c.update(fl_x=10 ** 400), "'fl_x': expected a number of pixels"),
    (lambda c: c.update(w=10 ** 400, h=24), "'w' must be a whole number of pixels, got 1000"),
    (lambda c: c.update(w=1e300, h=24), "'w' must be a whole number of pixels, got 1e+300 (expected 1 to 2^24)"),
    (lambda c: c.update(camera_angle_x=math.nan), "'camera_angle_x' must be a field of view in (0, pi) radians"),
    (lambda c: c["frames"][0]["transform_matrix"][0].__setitem__(3, 10 ** 400),
     "frame 0: 'transform_matrix' must be a 4x4 list of numbers (whole ones within +-2^24)"),
    (lambda c: c["frames"][1]["transform_matrix"][0].__setitem__(3, math.inf),
     "frame 1: 'transform_matrix' must be a rigid camera pose, but it is not finite"),
    (lambda c: c.update(applied_transform=[[1, 0, 0, math.nan], [0, 1, 0, 0], [0, 0, 1, 0]]),
     "'applied_transform' must be a 3x4 (or 4x4) list of finite numbers within +-2^24"),
])
def test_a_transforms_value_of_the_wrong_type_or_not_finite_is_one_line(tmp_path, change, says):
    path = ngp_file(tmp_path)
    content = json.loads(path.read_text())
    change(content)
    path.write_text(json.dumps(content))
    with pytest.raises(DatasetError) as caught:
        capture = read_capture(path)
        frame_lens_fields(capture.frames[0], capture.defaults, (24, 24))
    assert one_line_naming(caught.value, str(path), says), caught.value


@settings(max_examples=100, deadline=None)
@given(key=st.sampled_from(["camera_model", "fl_x", "fl_y", "cx", "cy", "k1", "p2", "k4"]), value=ANY_VALUE)
def test_a_lens_record_key_of_any_value_is_a_lens_or_an_error_naming_the_key(key, value):
    record = {"camera_model": "OPENCV", "fl_x": 20.0, "fl_y": 21.0, "cx": 12.0, "cy": 11.0, key: value}
    try:
        lens = read_lens_record(record)
    except LensRecordError as error:
        assert error.key == key and str(error).startswith(f"'{key}': ") and "\n" not in str(error)
        return
    assert torch.isfinite(lens.params).all() and torch.isfinite(lens.distortion).all()
    if key in ("fl_x", "fl_y", "cx", "cy"):
        assert lens.params[["fl_x", "fl_y", "cx", "cy"].index(key)].item() == value


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(value=ANY_VALUE)
def test_a_blender_field_of_view_of_any_value_is_read_or_one_line(tmp_path, value):
    with tempfile.TemporaryDirectory(dir=tmp_path) as folder:
        path = Path(folder) / "transforms_train.json"
        pose = scene_cameras("train", 1)[0].tolist()
        path.write_text(json.dumps({"camera_angle_x": value, "frames": [{"file_path": "r_0", "transform_matrix": pose}]}))
        try:
            angle, _ = read_transforms(path)
        except DatasetError as error:
            assert one_line_naming(error, str(path), "'camera_angle_x' must be a field of view in (0, pi) radians")
            return
        assert 0 < angle < math.pi and angle == value


def camera_file(root: Path, **keys) -> Path:
    """A render's cameras.json of two cameras, with ``keys`` over its own."""
    path = CameraPath("orbit", scene_cameras("test", 2), 8, 8, Intrinsics.pinhole(10.0, 8, 8), 30.0)
    root.mkdir(parents=True, exist_ok=True)
    (root / "cameras.json").write_text(json.dumps({**path.record(), **keys}))
    return root / "cameras.json"


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(key=st.sampled_from(["path", "fps", "height", "width", "camera_model", "fl_x", "k1", "c2w"]), value=ANY_VALUE)
def test_a_camera_file_value_of_any_type_is_read_or_one_line_naming_the_key(tmp_path, key, value):
    with tempfile.TemporaryDirectory(dir=tmp_path) as folder:
        path = camera_file(Path(folder), **{key: value})
        try:
            cameras = read_camera_path(path)
        except NerfexpError as error:
            # a frame too large for this machine's memory is named by its size, which the message gives
            named = f"'{key}'" if key not in ("height", "width") or "memory" not in str(error) else "a frame of"
            assert one_line_naming(error, f"--cameras {path}", named), error
            return
        assert cameras.name == value if key == "path" else True
        assert math.isfinite(cameras.fps) and torch.isfinite(cameras.c2w).all()


@pytest.mark.parametrize(("keys", "says"), [
    ({"camera_model": ["PINHOLE"]}, "key 'camera_model': expected one of PINHOLE"),
    ({"path": ["orbit"]}, "key 'path': expected a text (the path's name), got ['orbit']"),
    ({"c2w": [[[1, 0, 0, 10 ** 400], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]]},
     "item 0 is not a 4 x 4 matrix of numbers (whole ones within +-2^24)"),
    ({"fps": math.nan}, "key 'fps': expected a number of frames per second in [0.001, 1000], got nan"),
])
def test_a_camera_files_odd_values_are_named(tmp_path, keys, says):
    path = camera_file(tmp_path, **keys)
    with pytest.raises(NerfexpError) as caught:
        read_camera_path(path)
    assert one_line_naming(caught.value, f"--cameras {path}", says), caught.value


@pytest.mark.parametrize(("column", "value", "says"), [
    (16, 1e300, "row 0: depth bounds must satisfy 0 < near < far <= 2^24 (scene units), got [2.0, 1e+300]"),
    (14, 1e300, "row 0: height, width and focal must be positive (height and width whole numbers of pixels up to"),
    (14, 1e-30, "focal in [2^-24, 2^24] pixels), got [3.0, 4.0, 1e-30]"),
    (9, 4.5, "row 0: height, width and focal must be positive"),
    (4, 2.0 ** 30, "row 0: height, width and focal must be positive"),
])
def test_an_llff_row_out_of_range_is_one_line(tmp_path, column, value, says):
    # poses_bounds.npy: per image a 3x5 matrix row-major (its last column height, width, focal: entries 4, 9,
    # 14), then near and far (15, 16); a height of 3, width 4 and focal 3 as written
    bounds = torch.tensor([[2.0, 6.0]]).expand(2, 2)
    write_llff(tmp_path, torch.rand(2, 3, 4, 3), scene_cameras("train", 2), 3.0, bounds)
    rows = np.load(tmp_path / "poses_bounds.npy")
    rows[0, column] = value
    np.save(tmp_path / "poses_bounds.npy", rows)
    with pytest.raises(DatasetError) as caught:
        read_poses_bounds(tmp_path / "poses_bounds.npy")
    assert one_line_naming(caught.value, str(tmp_path / "poses_bounds.npy"), says), caught.value


@pytest.mark.parametrize(("model", "params", "says"), [
    ("SIMPLE_PINHOLE", [math.nan, 4, 3], "camera parameters [nan, 4.0, 3.0]: expected focal lengths in [2^-24, 2^24]"),
    ("PINHOLE", [10, 10, 1e300, 3], "camera parameters [10.0, 10.0, 1e+300, 3.0]: expected"),
    ("SIMPLE_RADIAL", [10, 4, 3, math.inf], "coefficients within +-1e+06"),
])
def test_a_colmap_camera_out_of_a_lens_records_ranges_is_one_line(model, params, says):
    with pytest.raises(DatasetError) as caught:
        colmap_lens(model, params, "sparse/0: camera 1")
    assert one_line_naming(caught.value, "sparse/0: camera 1", says), caught.value


def test_a_colmap_camera_placed_beyond_2_24_is_one_line(tmp_path):
    # a text model (COLMAP 3's format) whose one image sits 1e30 units from the origin (t = (0, 0, 1e30))
    model = tmp_path / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text("1 SIMPLE_PINHOLE 8 6 10 4 3\n")
    (model / "images.txt").write_text("1 1 0 0 0 0 0 1e30 1 a.png\n4 3 1\n2 1 0 0 0 0 0 4 1 b.png\n4 3 1\n")
    (model / "points3D.txt").write_text("1 0 0 0 255 255 255 0 1 0 2 0\n")
    (tmp_path / "images").mkdir()
    for name in ("a.png", "b.png"):
        (tmp_path / "images" / name).write_bytes(png_bytes(np.zeros((6, 8, 3), dtype=np.uint8)))
    with pytest.raises(DatasetError) as caught:
        load_colmap(tmp_path)
    assert one_line_naming(caught.value, str(model), "image 1 (a.png): the pose must be a rigid camera pose, but its position"), caught.value


@pytest.mark.parametrize("source", [{"video": "clip.mp4", "fps": 10 ** 400}, {"video": "clip.mp4", "fps": math.nan},
                                    {"video": ["clip.mp4"], "fps": 2.0}, {"video": "clip.mp4", "fps": "2"}, [2.0]])
def test_a_frames_folder_whose_source_is_odd_is_refused_in_one_line(tmp_path, source):
    # frames/source.json says which video and fps the frames were taken from; anything else is not nerfexp's
    (tmp_path / "frames").mkdir()
    (tmp_path / "frames" / "source.json").write_text(json.dumps(source))
    with pytest.raises(DatasetError) as caught:
        cached_frames(tmp_path / "frames", "clip.mp4", 2.0)
    assert one_line_naming(caught.value, str(tmp_path / "frames"), "holds no readable source.json"), caught.value
    (tmp_path / "frames" / "source.json").write_text(json.dumps({"video": "clip.mp4", "fps": 2}))
    assert cached_frames(tmp_path / "frames", "clip.mp4", 2.0)  # as nerfexp writes it: its frames are reused
