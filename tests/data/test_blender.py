"""The Blender (NeRF synthetic) format: round trips, downscaling, frame selection and clear errors."""

import json
import math
import re

import numpy as np
import pytest
import torch
from PIL import Image

from nerfexp.data.blender import BlenderScene, load_blender, write_blender
from nerfexp.data.datamodule import RayDataModule
from nerfexp.data.views import Views
from nerfexp.errors import DatasetError
from nerfexp.geometry.lenses import Intrinsics
from tests.data.blender_views import ANGLE, make_views


def assert_centred_pinholes(views: Views, focal: float) -> None:
    """Every view's lens is an undistorted pinhole of focal length ``focal`` (both axes) centred on its image."""
    expected = torch.tensor([focal, focal, views.width / 2, views.height / 2], dtype=torch.float64)
    torch.testing.assert_close(views.intrinsics.params, expected.expand(len(views), 4))
    assert not views.intrinsics.is_distorted().any()


@pytest.fixture
def scene(tmp_path):
    views = make_views()
    write_blender(tmp_path, "train", views, ANGLE)
    return tmp_path, views


def edit_transforms(root, edit):
    path = root / "transforms_train.json"
    content = json.loads(path.read_text())
    edit(content)
    path.write_text(json.dumps(content))


def test_round_trip(scene):
    root, views = scene
    assert (root / "train" / "r_5.png").is_file()
    assert json.loads((root / "transforms_train.json").read_text())["frames"][2]["file_path"] == "./train/r_2"
    loaded = load_blender(root, "train")
    assert torch.equal(loaded.c2w, views.c2w)
    torch.testing.assert_close(loaded.rgba, views.rgba, atol=0.5 / 255, rtol=0)  # 8-bit rounding
    assert_centred_pinholes(loaded, 0.5 * 8 / math.tan(0.5 * ANGLE))
    assert not list(root.rglob("*.tmp"))  # no temporary files left behind


def test_downscale_by_two_halves_size_and_focal(scene):
    root, _ = scene
    full, half = load_blender(root, "train"), load_blender(root, "train", downscale=2)
    assert half.rgba.shape == (6, 3, 4, 4)
    assert_centred_pinholes(half, full.intrinsics.params[0, 0].item() / 2)
    # alpha is the block mean; colour is the alpha-weighted block mean
    blocks = full.rgba.reshape(6, 3, 2, 4, 2, 4)
    alpha = blocks[..., 3].mean((2, 4))
    torch.testing.assert_close(half.rgba[..., 3], alpha)
    weighted = (blocks[..., :3] * blocks[..., 3:]).mean((2, 4)) / alpha[..., None]
    torch.testing.assert_close(half.rgba[..., :3][alpha > 0], weighted[alpha > 0])


def test_downscale_does_not_bleed_transparent_colour(tmp_path):
    # One opaque red pixel in a 2x2 block of transparent blue: alpha 1/4, colour pure red.
    rgba = torch.zeros(1, 2, 2, 4)
    rgba[..., 2] = 1
    rgba[0, 0, 0] = torch.tensor([1.0, 0, 0, 1])
    views = Views(rgba=rgba, c2w=torch.eye(4)[None], intrinsics=Intrinsics.pinhole(1.0, 2, 2, (1,)))
    write_blender(tmp_path, "train", views, ANGLE)
    assert load_blender(tmp_path, "train", downscale=2).rgba[0, 0, 0].tolist() == [1, 0, 0, 0.25]


def test_downscale_not_dividing_the_size_keeps_the_whole_image(tmp_path):
    write_blender(tmp_path, "train", make_views(n=1, height=5, width=7), ANGLE)
    views = load_blender(tmp_path, "train", downscale=2)
    assert views.rgba.shape == (1, 2, 3, 4)
    fx, _, cx, cy = views.intrinsics.params[0].tolist()  # the field of view across the 3 columns kept
    assert fx == pytest.approx(0.5 * 3 / math.tan(0.5 * ANGLE)) and (cx, cy) == (1.5, 1.0)


@pytest.mark.parametrize("stride, max_views, frames", [
    (1, None, [0, 1, 2, 3, 4, 5]), (2, None, [0, 2, 4]), (1, 2, [0, 1]), (2, 2, [0, 2]), (4, 10, [0, 4]),
    (1, 6, list(range(6))),
])
def test_stride_then_max_views_select_frames(scene, stride, max_views, frames):
    root, views = scene
    loaded = load_blender(root, "train", max_views=max_views, stride=stride)
    assert torch.equal(loaded.c2w, views.c2w[frames])
    torch.testing.assert_close(loaded.rgba, views.rgba[frames], atol=0.5 / 255, rtol=0)


def test_rgb_png_without_alpha_is_opaque(scene):
    root, _ = scene
    rgb = np.arange(6 * 8 * 3, dtype=np.uint8).reshape(6, 8, 3)
    Image.fromarray(rgb, "RGB").save(root / "train" / "r_0.png")
    image = load_blender(root, "train", max_views=1).rgba[0]
    assert (image[..., 3] == 1).all()
    assert torch.equal(image[..., :3], torch.from_numpy(rgb).float() / 255)


def test_file_path_with_extension_and_without_dot_slash(scene):
    root, views = scene
    edit_transforms(root, lambda c: c["frames"][0].update(file_path="train/r_3.png"))
    # frame 0 alone: with frame 3 (./train/r_3) the split would name r_3.png twice, which is refused
    assert torch.equal(load_blender(root, "train", max_views=1).c2w[0], views.c2w[0])  # pose from frame 0, image of r_3
    torch.testing.assert_close(load_blender(root, "train", max_views=1).rgba[0], views.rgba[3], atol=0.5 / 255, rtol=0)


@pytest.mark.parametrize("spelling", ["./train/r_2", "train//r_2.png", "./train/./r_2.png"])
def test_one_image_twice_in_a_split_is_refused_before_it_is_read(scene, spelling):
    root, _ = scene
    edit_transforms(root, lambda c: c["frames"][4].update(file_path=spelling))
    (root / "train" / "r_0.png").unlink()  # refused by the names: no image read (r_0 would be missing)
    with pytest.raises(DatasetError) as caught:
        load_blender(root, "train")
    transforms = root / "transforms_train.json"
    assert str(caught.value) == (f"{transforms}: frame 2 (./train/r_2) and {transforms}: frame 4 ({spelling}) name "
                                 f"one file ({root / 'train' / 'r_2.png'}): one view counted twice; list each image "
                                 "once")


@pytest.mark.parametrize("spelling", ["./train/r_1", "train//r_1.png", "link"])
def test_a_test_frame_naming_a_training_image_is_refused_before_training(scene, spelling):
    root, views = scene
    write_blender(root, "val", make_views(n=1, seed=1), ANGLE)
    write_blender(root, "test", make_views(n=2, seed=2), ANGLE)
    if spelling == "link":
        (root / "test" / "r_1.png").unlink()
        (root / "test" / "r_1.png").symlink_to(root / "train" / "r_1.png")
        spelling = "./test/r_1"
    path = root / "transforms_test.json"
    content = json.loads(path.read_text())
    content["frames"][1]["file_path"] = spelling
    path.write_text(json.dumps(content))
    data = RayDataModule(BlenderScene(root=str(root)), batch_rays=64)
    with pytest.raises(DatasetError) as caught:
        data.setup("fit")
    assert str(caught.value).startswith(f"the test view {path}: frame 1 ({spelling}) and the training view "
                                        f"{root / 'transforms_train.json'}: frame 1 (./train/r_1) are one view (they "
                                        "name one file")
    content["frames"][1]["file_path"] = "./test/r_0"  # a test view twice: the training views are not among them
    path.write_text(json.dumps(content))
    with pytest.raises(DatasetError, match=r"frame 0 \(./test/r_0\) and .* frame 1 \(./test/r_0\) name one file"):
        RayDataModule(BlenderScene(root=str(root)), batch_rays=64).setup("fit")


def test_honest_splits_load(scene):
    root, views = scene
    write_blender(root, "val", make_views(n=1, seed=1), ANGLE)
    write_blender(root, "test", make_views(n=2, seed=2), ANGLE)
    data = RayDataModule(BlenderScene(root=str(root)), batch_rays=64)
    data.setup("fit")
    assert torch.equal(data.train_views().c2w, views.c2w)
    assert [source.path for source in data.scored_views("fit")["test"].sources] == [
        root / "test" / f"r_{i}.png" for i in range(2)]


def write_png(path, height, width):
    Image.fromarray(np.zeros((height, width, 4), dtype=np.uint8), "RGBA").save(path)


def break_root(root):
    return root / "nowhere", {}


def break_split(root):
    return root, {"split": "val"}


def break_json(root):
    (root / "transforms_train.json").write_text('{\n  "camera_angle_x": 0.7,\n  "frames": [,]\n}')
    return root, {}


def drop(key):
    def edit(root):
        edit_transforms(root, lambda c: c.pop(key))
        return root, {}
    return edit


def drop_in_frame(key):
    def edit(root):
        edit_transforms(root, lambda c: c["frames"][1].pop(key))
        return root, {}
    return edit


def set_matrix(value):
    def edit(root):
        edit_transforms(root, lambda c: c["frames"][4].update(transform_matrix=value))
        return root, {}
    return edit


def remove_image(root):
    (root / "train" / "r_3.png").unlink()
    return root, {}


def resize_image(root):
    write_png(root / "train" / "r_2.png", 6, 9)
    return root, {}


def empty_frames(root):
    edit_transforms(root, lambda c: c.update(frames=[]))
    return root, {}


def argument(**options):
    return lambda root: (root, options)


@pytest.mark.parametrize("breakage, message", [
    (break_root, "data.root .*nowhere does not exist.*config key data.root"),
    (break_split, "transforms_val.json does not exist; transforms files in .*: transforms_train.json"),
    (break_json, r"transforms_train.json: not JSON \(line 3, column"),
    (drop("camera_angle_x"), "transforms_train.json: missing key 'camera_angle_x'"),
    (drop("frames"), "transforms_train.json: missing key 'frames'"),
    (drop_in_frame("file_path"), "frame 1: missing key 'file_path'"),
    (drop_in_frame("transform_matrix"), "frame 1: missing key 'transform_matrix'"),
    (set_matrix([[1, 0, 0, 0]] * 3), "frame 4: 'transform_matrix' must be a 4x4"),
    (set_matrix([[1, 0, 0, "x"]] * 4), "frame 4: 'transform_matrix' must be a 4x4"),
    (set_matrix(7), "frame 4: 'transform_matrix' must be a 4x4"),
    (set_matrix([[0] * 4] * 4), re.escape("frame 4: 'transform_matrix' must be a rigid camera pose, but its last "
                                          "row is [0.0, 0.0, 0.0, 0.0], not [0, 0, 0, 1]")),
    (set_matrix([[2, 0, 0, 0], [0, 2, 0, 0], [0, 0, 2, 0], [0, 0, 0, 1]]),
     "frame 4: .* but its rotation is not orthonormal \\(R\\^T R differs from the identity by 3\\)"),
    (set_matrix([[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), "a reflection \\(determinant -1\\)"),
    (set_matrix([[float("nan"), 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), "frame 4: .* it is not finite"),
    (remove_image, re.escape("r_3.png does not exist")),
    (resize_image, "r_2.png: image size 9x6 differs from .*r_0.png \\(8x6\\)"),
    (empty_frames, "'frames' must be a non-empty list"),
    (argument(max_views=0), "max_views must be >= 1"),
    (argument(stride=0), "stride must be >= 1"),
    (argument(downscale=0), "downscale must be >= 1"),
    (argument(downscale=7), "downscale 7 is larger than the images"),
])
def test_errors_name_the_file_or_key(scene, breakage, message):
    root, options = breakage(scene[0])
    options = {"split": "train", **options}
    with pytest.raises(DatasetError, match=message):
        load_blender(root, **options)


def test_scene_caps_the_image_side_for_cpu_sized_runs(tmp_path):
    # 12 x 16 images capped at 5 pixels: the factor is ceil(16 / 5) = 4, giving 3 x 4 and focal / 4,
    # the same as asking for downscale=4 directly; a cap the images already fit changes nothing.
    from nerfexp.data.blender import BlenderScene

    write_blender(tmp_path, "train", make_views(height=12, width=16), ANGLE)
    capped = BlenderScene(str(tmp_path), max_side=5).views("train")
    direct = load_blender(tmp_path, "train", downscale=4)
    assert capped.rgba.shape == (6, 3, 4, 4)
    torch.testing.assert_close(capped.intrinsics.params, direct.intrinsics.params)
    assert_centred_pinholes(capped, 0.5 * 4 / math.tan(0.5 * ANGLE))
    torch.testing.assert_close(capped.rgba, direct.rgba)
    assert BlenderScene(str(tmp_path), max_side=16).views("train").rgba.shape == (6, 12, 16, 4)
