"""A training view nearly copied into the test split is refused before training, in every format nerfexp reads
(``nerfexp.data.views.check_distinct_views``): one level of one pixel changed, a JPEG re-save, an exact copy with
1e-6 on a translation entry; and the held-out views of the scenes nerfexp ships, and of their exports, are not."""

import io
import json
import math
import re

import numpy as np
import pytest
import torch
from PIL import Image

from nerfexp.data.blender import BlenderScene, write_blender
from nerfexp.data.colmap import ColmapScene
from nerfexp.data.datamodule import RayDataModule
from nerfexp.data.llff import LLFFScene, c2w_to_llff, write_llff
from nerfexp.data.nerfstudio import NerfstudioScene
from nerfexp.data.procedural import CAMERA_ANGLE_X, ProceduralScene, load_procedural, scene_cameras
from nerfexp.data.transforms_file import TRANSFORMS, write_nerfstudio
from nerfexp.data.views import CENTRE_FRACTION, IMAGE_PSNR_DB, RAY_DEGREES, Views
from nerfexp.errors import DatasetError
from nerfexp.geometry.cameras import focal_from_fov
from nerfexp.pixels import png_bytes, to_uint8
from tests.helpers import run_nerfexp

SIZE = 24
COPIED = 3  # the training view copied into the test split
WHITE = np.full(3, 255.0)


@pytest.fixture(scope="module")
def rendered() -> dict[str, Views]:
    """The built-in scene at 24 x 24: 6 training, 1 validation and 2 test views, each its own camera."""
    return {split: load_procedural(split, n, SIZE, SIZE, supersample=1)
            for split, n in (("train", 6), ("val", 1), ("test", 2))}


def over_white(rgba8: np.ndarray) -> np.ndarray:
    """8-bit RGB [H, W, 3] of straight-alpha 8-bit RGBA [H, W, 4] composited over white, as a photograph is."""
    alpha = rgba8[..., 3:] / 255.0
    return np.round(rgba8[..., :3] * alpha + WHITE * (1 - alpha)).astype(np.uint8)


def jpeg(rgb8: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(rgb8).save(buffer, format="JPEG")  # Pillow's default quality, 75
    return buffer.getvalue()


def psnr_over_white(rgba8: np.ndarray, image: bytes) -> float:
    """The PSNR of the image file ``image``, read, against ``rgba8`` composited over white: worked out here with
    NumPy in float64, apart from nerfexp's ``image_psnr``."""
    read = np.asarray(Image.open(io.BytesIO(image)).convert("RGBA"), dtype=np.float64) / 255
    target = rgba8 / 255.0
    scored = [rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:]) for rgba in (read, target)]
    return -10 * math.log10(np.mean((scored[0] - scored[1]) ** 2))


def one_level(rgba8: np.ndarray, c2w: torch.Tensor) -> tuple[str, bytes, torch.Tensor]:
    """The training image with one value of one opaque pixel changed by 1/255, at the training view's pose."""
    changed = rgba8.copy()
    i, j = np.argwhere(changed[..., 3] == 255)[0]
    changed[i, j, 0] = changed[i, j, 0] + 1 if changed[i, j, 0] < 255 else 254
    return ".png", png_bytes(changed), c2w


def jpeg_resave(rgba8: np.ndarray, c2w: torch.Tensor) -> tuple[str, bytes, torch.Tensor]:
    """The training image composited over white and saved as a JPEG, at the training view's pose."""
    return ".jpg", jpeg(over_white(rgba8)), c2w


def moved_a_millionth(rgba8: np.ndarray, c2w: torch.Tensor) -> tuple[str, bytes, torch.Tensor]:
    """An exact copy of the training image (another file), at the training pose with 1e-6 on its x translation."""
    moved = c2w.clone()
    moved[0, 3] += 1e-6
    return ".png", png_bytes(rgba8), moved


def expected_likeness(kind, rgba8: np.ndarray, image: bytes) -> str:
    """The part of the message that says how alike the copy and its training view are, by kind: the same pose
    with the PSNR worked out by ``psnr_over_white``, or identical images with the camera moved (and, where a
    format makes a camera look at a point, turned by as little)."""
    if kind is moved_a_millionth:
        return r"their cameras [0-9.e-]+ of the cameras' spread and [0-9.e-]+ degrees apart, their images identical"
    return (r"their cameras 0 of the cameras' spread and 0 degrees apart, their images at "
            + re.escape(f"{psnr_over_white(rgba8, image):.1f}") + " dB PSNR")


def read_rgba8(path) -> np.ndarray:
    """The image file ``path`` as 8-bit RGBA [H, W, 4] (opaque where it has no alpha)."""
    return np.asarray(Image.open(path).convert("RGBA"))


def blender_scene(root, rendered, near_copy) -> tuple:
    """The views as a Blender scene and a ``near_copy`` of training view ``COPIED`` appended to the test split
    (whose images are all made JPEGs where the copy is one: a split's images all have alpha or none): the scene,
    the copy's and the training view's names, the training image and the copy's file."""
    for split, views in rendered.items():
        write_blender(root, split, views, CAMERA_ANGLE_X)
    train = json.loads((root / "transforms_train.json").read_text())["frames"][COPIED]
    rgba8 = read_rgba8(root / f"{train['file_path']}.png")
    suffix, image, c2w = near_copy(rgba8, torch.tensor(train["transform_matrix"], dtype=torch.float64))
    path = root / "transforms_test.json"
    content = json.loads(path.read_text())
    if suffix == ".jpg":
        for frame in content["frames"]:
            png = root / f"{frame['file_path']}.png"
            (root / f"{frame['file_path']}.jpg").write_bytes(jpeg(over_white(read_rgba8(png))))
            frame["file_path"] += ".jpg"
    (root / "test" / f"copy{suffix}").write_bytes(image)
    content["frames"].append({"file_path": f"./test/copy{suffix}", "transform_matrix": c2w.tolist()})
    path.write_text(json.dumps(content))
    return (BlenderScene(root=str(root), n_val=1), f"{path}: frame 2 (./test/copy{suffix})",
            f"{root / 'transforms_train.json'}: frame {COPIED} (./train/r_{COPIED})", rgba8, image)


def nerfstudio_scene(root, rendered, near_copy) -> tuple:
    """The views as a nerfstudio scene, the near copy a frame of its own in ``test_filenames``."""
    write_nerfstudio(root, rendered.items())
    path = root / TRANSFORMS
    content = json.loads(path.read_text())
    train = content["frames"][COPIED]
    rgba8 = read_rgba8(root / train["file_path"])
    suffix, image, c2w = near_copy(rgba8, torch.tensor(train["transform_matrix"], dtype=torch.float64))
    (root / "images" / f"copy{suffix}").write_bytes(image)
    content["frames"].append({"file_path": f"images/copy{suffix}", "transform_matrix": c2w.tolist()})
    content["test_filenames"].append(f"images/copy{suffix}")
    path.write_text(json.dumps(content))
    return (NerfstudioScene(root=str(root), n_val=1), f"{path}: frame 9 (images/copy{suffix})",
            f"{path}: frame {COPIED} ({train['file_path']})", rgba8, image)


def llff_scene(root, rendered, near_copy) -> tuple:
    """The views as an LLFF scene in the order that its holdout of 7 splits them: a test view, the 6 training
    views, the near copy (row 7, a test view); world rays between bounds that hold its depth bounds (2 and 6 at
    every row)."""
    train, test = rendered["train"], rendered["test"]
    rgb = torch.cat([test.rgb_on(torch.ones(3))[:1], train.rgb_on(torch.ones(3))])
    c2w = torch.cat([test.c2w[:1], train.c2w]).double()
    rows, focal = root / "poses_bounds.npy", focal_from_fov(SIZE, CAMERA_ANGLE_X)
    write_llff(root, rgb, c2w, focal, torch.tensor([[2.0, 6.0]] * 7))
    trained = root / "images" / f"00{COPIED + 1}.png"
    rgba8 = read_rgba8(trained)
    suffix, image, pose = near_copy(rgba8, c2w[COPIED + 1])
    (root / "images" / f"007{suffix}").write_bytes(image)
    row = torch.cat([c2w_to_llff(pose[None], SIZE, SIZE, focal).reshape(1, 15), torch.tensor([[2.0, 6.0]])], -1)
    np.save(rows, np.concatenate([np.load(rows), row.numpy()]))
    return (LLFFScene(root=str(root), factor=1, holdout=7, n_val=1, ndc=False, near=1.0, far=5.0),
            f"{root / 'images' / f'007{suffix}'} (row 7 of {rows})", f"{trained} (row {COPIED + 1} of {rows})", rgba8,
            image)


def colmap_scene(root, rendered, near_copy) -> tuple:
    """The built-in scene's cameras as a hand-made COLMAP model (``tests.data.photographs``: cameras looking at the
    origin, z up, as the built-in scene's are; its 8 x 6 images) of 5 images, the near copy the last: its holdout
    of 2 makes images 1, 3 and 5 the test views and 2 and 4 the training ones; image 2 is the training view
    copied."""
    from tests.data.photographs import HEIGHT, WIDTH, hand_made_model  # pycolmap

    train, test = (load_procedural(split, n, HEIGHT, WIDTH, supersample=1) for split, n in (("train", 6), ("test", 2)))
    views = [(test, 0), (train, COPIED), (test, 1), (train, 0)]
    images = root / "images"
    images.mkdir()
    for i, (v, k) in enumerate(views, start=1):
        (images / f"view_{i}.png").write_bytes(png_bytes(to_uint8(v.rgb_on(torch.ones(3))[k])))
    rgba8 = read_rgba8(images / "view_2.png")
    _, image, c2w = near_copy(rgba8, train.c2w[COPIED].double())
    (images / "view_5.png").write_bytes(image)  # a JPEG too: COLMAP's model names it view_5.png
    model = root / "sparse" / "0"
    model.mkdir(parents=True)
    eyes = [tuple(v.c2w[k, :3, 3].double().tolist()) for v, k in views] + [tuple(c2w[:3, 3].tolist())]
    hand_made_model(ring=eyes).write_text(model)
    return (ColmapScene(root=str(root), holdout=2, n_val=1), str(images / "view_5.png"), str(images / "view_2.png"),
            rgba8, image)


FORMATS = {"blender": blender_scene, "nerfstudio": nerfstudio_scene, "llff": llff_scene, "colmap": colmap_scene}


@pytest.mark.parametrize("kind", [one_level, jpeg_resave, moved_a_millionth], ids=lambda kind: kind.__name__)
@pytest.mark.parametrize("form", FORMATS)
def test_a_near_copy_of_a_training_view_in_the_test_split_is_refused_before_training(tmp_path, rendered, form,
                                                                                     kind):
    scene, copy_name, train_name, rgba8, image = FORMATS[form](tmp_path, rendered, kind)
    with pytest.raises(DatasetError) as caught:
        RayDataModule(scene, batch_rays=64).setup("fit")
    tolerances = (f"one view is cameras within {CENTRE_FRACTION:g} of the spread and {RAY_DEGREES:g} degrees, images "
                  f"at {IMAGE_PSNR_DB:g} dB or more")
    expected = (re.escape(f"the test view {copy_name} and the training view {train_name} are one view (")
                + expected_likeness(kind, rgba8, image)
                + re.escape(f": {tolerances}): a score on views training saw is no test score; keep it in one split"))
    assert re.fullmatch(expected, str(caught.value)), str(caught.value)


def test_the_held_out_views_of_the_built_in_scene_are_not_refused():
    # its training cameras on a spiral, its validation and test cameras on orbits of their own (scene_cameras)
    data = RayDataModule(ProceduralScene(image_size=16, supersample=1), batch_rays=64)
    data.setup("fit")
    assert data.split_check["views"] == 110 and data.split_check["image_pairs"] == 0


@pytest.mark.parametrize("export", [["--scene", "builtin"], ["--scene", "glossy"],
                                    ["--scene", "builtin", "--format", "nerfstudio", "--lens", "real", "--occluders"],
                                    ["--scene", "glossy", "--format", "nerfstudio", "--appearance-changes", "train"]],
                         ids=" ".join)
def test_the_held_out_views_of_the_scenes_nerfexp_exports_are_not_refused(tmp_path, export):
    exported = run_nerfexp(str(tmp_path / "scene"), "--resolution", "16", "--supersample", "1", *export, cwd=tmp_path,
                           script="nerfexp-scene")
    assert exported.returncode == 0, exported.stderr[-2000:]
    scene = (NerfstudioScene if "nerfstudio" in export else BlenderScene)(root=str(tmp_path / "scene"))
    data = RayDataModule(scene, batch_rays=64)
    data.setup("fit")
    # every view read of the export (100 training, the first 2 of its 10 validation views, 20 test), no camera near
    # another split's
    assert data.split_check["views"] == 100 + 2 + 20
    assert data.split_check["image_pairs"] == 0


def test_a_built_in_test_camera_that_falls_on_a_training_camera_is_refused():
    # the training spiral crosses the test orbit's elevation: with 51 training and 15 test views, test camera 7 lies
    # within a thousandth of a unit of training camera 23 (worked out here from the cameras alone), and its image
    # is that view's
    train, test = scene_cameras("train", 51), scene_cameras("test", 15)
    centres = torch.cat([train, test, scene_cameras("val", 2)])[:, :3, 3].numpy()
    spread = np.sqrt(np.mean(np.sum((centres - centres.mean(0)) ** 2, -1)))
    assert np.linalg.norm(centres[51 + 7] - centres[23]) / spread < CENTRE_FRACTION
    axes = -torch.stack([test[7, :3, 2], train[23, :3, 2]]).numpy()  # the viewing directions
    assert math.degrees(math.acos(min(1.0, float(axes[0] @ axes[1])))) < RAY_DEGREES
    data = RayDataModule(ProceduralScene(image_size=16, supersample=1, n_train=51, n_test=15), batch_rays=64)
    with pytest.raises(DatasetError, match=r"^the test view 7 and the training view 23 are one view \(their cameras "):
        data.setup("fit")
