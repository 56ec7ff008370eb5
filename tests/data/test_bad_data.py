"""Image files, transforms files, poses_bounds.npy and the file paths datasets name that are damaged or hostile:
each either loads exactly what it holds or is a one-line DatasetError naming the file, never a traceback of
another kind and never wrong values. The fuzz tests generate the inputs (hypothesis)."""

import io
import json
import math
import re
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from nerfexp.data.blender import BlenderScene, load_blender, write_blender
from nerfexp.data.colmap import ColmapScene
from nerfexp.data.datamodule import RayDataModule
from nerfexp.data.images import MAX_PIXELS, read_image
from nerfexp.data.llff import read_poses_bounds
from nerfexp.data.nerfstudio import NerfstudioScene
from nerfexp.data.procedural import load_procedural
from nerfexp.data.transforms_file import TRANSFORMS, write_nerfstudio
from nerfexp.errors import DatasetError

FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def png_bytes_of(pixels: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(pixels).save(buffer, format="PNG")
    return buffer.getvalue()


def chunk(kind: bytes, data: bytes) -> bytes:
    """A PNG chunk with its length and a correct CRC-32."""
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def assert_one_line_naming(error: DatasetError, path: Path) -> None:
    message = str(error)
    assert str(path) in message and "\n" not in message, message


def test_a_16_bit_greyscale_png_is_read_at_its_values(tmp_path):
    values = np.array([[0, 257, 32896], [65535, 1000, 50000]], dtype=np.uint16)  # 257 k: exactly k in 8 bits
    path = tmp_path / "depth16.png"
    Image.fromarray(values).save(path)
    assert Image.open(path).mode.startswith("I")  # Pillow reads it as 16-bit integers
    rgba = read_image(path, "a test").numpy()
    expected = np.round(values / 257).astype(np.uint8)  # 0, 1, 128, 255, 4, 195
    assert np.array_equal(rgba[..., 0], expected) and np.array_equal(rgba[..., 2], expected)
    assert (rgba[..., 3] == 255).all()


def test_a_flipped_byte_in_a_pngs_image_data_is_an_error_not_wrong_pixels(tmp_path):
    pixels = np.random.default_rng(0).integers(0, 256, (16, 16, 4), dtype=np.uint8)
    data = bytearray(png_bytes_of(pixels))
    idat = data.index(b"IDAT")
    data[idat + 10] ^= 0x40  # inside the compressed image data, which Pillow decodes without its checksum
    path = tmp_path / "r_0.png"
    path.write_bytes(bytes(data))
    damaged = re.escape("a damaged or unreadable image file (broken PNG file (bad header checksum in b'IDAT'))")
    with pytest.raises(DatasetError, match=damaged) as caught:
        read_image(path, "a test")
    assert_one_line_naming(caught.value, path)


def test_an_image_too_large_to_decode_safely_is_refused_before_decoding(tmp_path):
    side = int(np.sqrt(2 * MAX_PIXELS)) + 1  # past Pillow's bomb limit (twice MAX_IMAGE_PIXELS)
    header = struct.pack(">IIBBBBB", side, side, 8, 6, 0, 0, 0)  # RGBA, 8 bits
    path = tmp_path / "bomb.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\x00" * 64))
                     + chunk(b"IEND", b""))
    with pytest.raises(DatasetError, match=f"more than {MAX_PIXELS} pixels, which nerfexp does not decode") as caught:
        read_image(path, "a test")
    assert_one_line_naming(caught.value, path)


PIXELS = np.random.default_rng(1).integers(0, 256, (8, 8, 4), dtype=np.uint8)
PNG = png_bytes_of(PIXELS)


@FUZZ
@given(flips=st.lists(st.tuples(st.integers(0, len(PNG) - 1), st.integers(1, 255)), min_size=1, max_size=3))
def test_fuzz_damaged_pngs_load_exactly_or_fail_naming_the_file(tmp_path_factory, flips):
    data = bytearray(PNG)
    for position, mask in flips:
        data[position] ^= mask
    path = tmp_path_factory.mktemp("png") / "r_0.png"
    path.write_bytes(bytes(data))
    try:
        rgba = read_image(path, "a test").numpy()
    except DatasetError as error:
        assert_one_line_naming(error, path)
    else:
        assert np.array_equal(rgba, PIXELS)  # loaded: the pixels written, never others


FRAME_VALUES = st.one_of(
    st.none(), st.booleans(), st.integers(-3, 3), st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=4),
    st.lists(st.lists(st.one_of(st.floats(-2, 2), st.integers(-1, 1), st.just(float("nan"))), min_size=3, max_size=5),
             min_size=3, max_size=5))


@FUZZ
@given(angle=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=3), st.none()),
       matrix=FRAME_VALUES, file_path=st.one_of(st.just("./r_0"), st.just("r_0.png"), st.text(max_size=6)))
def test_fuzz_transforms_files_load_exactly_or_fail_naming_the_file(tmp_path_factory, angle, matrix, file_path):
    root = tmp_path_factory.mktemp("blender")
    Image.fromarray(PIXELS).save(root / "r_0.png")
    content = {"camera_angle_x": angle, "frames": [{"file_path": file_path, "transform_matrix": matrix}]}
    (root / "transforms_train.json").write_text(json.dumps(content))
    try:
        views = load_blender(root, "train")
    except DatasetError as error:
        assert str(root) in str(error) and "\n" not in str(error), str(error)
    else:  # loaded: the pose, angle and image written
        assert torch.equal(views.c2w[0], torch.tensor(matrix, dtype=torch.float32))
        fx, fy, cx, cy = views.intrinsics.params[0].tolist()  # a pinhole centred on the 8 x 8 image
        assert fx == fy == pytest.approx(0.5 * 8 / math.tan(0.5 * angle)) and (cx, cy) == (4.0, 4.0)
        assert torch.equal(views.rgba[0], torch.from_numpy(PIXELS).float() / 255)


@FUZZ
@given(rows=st.integers(1, 3), values=st.lists(st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                                                         st.floats(-5, 5)), min_size=17 * 3, max_size=17 * 3),
       rigid=st.booleans())
def test_fuzz_poses_bounds_load_exactly_or_fail_naming_the_file(tmp_path_factory, rows, values, rigid):
    array = np.array(values[:17 * rows], dtype=np.float64).reshape(rows, 17)
    if rigid:  # a valid pose in every row (the identity rotation in LLFF's axes) with the generated rest
        array[:, :15] = np.array([[0, 1, 0, 0, 4], [-1, 0, 0, 0, 4], [0, 0, 1, 0, 2]], dtype=np.float64).reshape(15)
    path = tmp_path_factory.mktemp("llff") / "poses_bounds.npy"
    np.save(path, array)
    try:
        poses, bounds = read_poses_bounds(path)
    except DatasetError as error:
        assert_one_line_naming(error, path)
    else:  # loaded: exactly the numbers stored
        assert np.array_equal(poses.reshape(rows, 15).numpy(), array[:, :15])
        assert np.array_equal(bounds.numpy(), array[:, 15:])


# A file path from a dataset's file that no file can have, or that the file system refuses to look up, put below the
# scene's image folder: each the parsed name's one line naming the file, the frame and the key, or where only the
# system can tell, the lookup's one line naming the file and what named it (nerfexp.reading.file_status)
UNNAMEABLE = {"a NUL byte": "a\x00b.png", "a lone surrogate": "\ud800b.png", "a name too long": "a" * 300 + ".png",
              "a path too long": "a/" * 2100 + "b.png"}


def parsed_reason(name: str) -> str | None:
    """Why ``name`` is refused where its file is parsed (None: only a lookup can tell)."""
    if "\0" in name:
        return "holds a NUL byte, which no file name can"
    if "\ud800" in name:
        return f"holds characters no file name can (surrogates not allowed at character {name.index(chr(0xd800))})"
    return None


def small_splits() -> dict:
    return {split: load_procedural(split, n, 8, 8, supersample=1) for split, n in (("train", 3), ("val", 1),
                                                                                    ("test", 1))}


def nerfstudio_naming(root: Path, key: str, bare: str) -> tuple:
    """A nerfstudio scene whose frame 1 (or the file, for 'ply_file_path') names ``images/{bare}`` under ``key``:
    the scene, the name, its error's start where the file is parsed, and what named it in a lookup's."""
    write_nerfstudio(root, small_splits().items())
    path, name = root / TRANSFORMS, f"images/{bare}"
    content = json.loads(path.read_text())
    for split_list in ("train_filenames", "val_filenames", "test_filenames"):
        content.pop(split_list)  # every 8th frame a test view: frame 1's file_path may be any name
    if key == "ply_file_path":
        content[key] = name
        where, named_by = f"{path}: '{key}'", f"{path}'s 'ply_file_path'"
    else:
        frame = content["frames"][1]
        where = f"{path}: frame 1: '{key}'"
        named_by = f"{path}: frame 1 ({name})" if key == "file_path" else \
            f"{path}: frame 1 ({frame['file_path']})'s mask_path"
        frame[key] = name
    path.write_text(json.dumps(content))
    return NerfstudioScene(root=str(root)), name, where, named_by


def blender_naming(root: Path, key: str, bare: str) -> tuple:
    for split, views in small_splits().items():
        write_blender(root, split, views, 0.7)
    path, name = root / "transforms_train.json", f"train/{bare}"
    content = json.loads(path.read_text())
    content["frames"][1][key] = name
    path.write_text(json.dumps(content))
    return BlenderScene(root=str(root), n_val=1), name, f"{path}: frame 1: '{key}'", f"{path}: frame 1 ({name})"


def colmap_naming(root: Path, key: str, bare: str) -> tuple:
    """A COLMAP text model whose image 3 is called ``bare`` (a text file holds any name without a space; a lone
    surrogate written as its UTF-8 bytes would be, which are no UTF-8 text)."""
    from tests.data.photographs import hand_made_model, write_images  # pycolmap

    model = root / "sparse" / "0"
    model.mkdir(parents=True)
    hand_made_model().write_text(model)
    images = model / "images.txt"
    images.write_bytes(images.read_bytes().replace(b"view_3.png", bare.encode("utf-8", "surrogatepass")))
    write_images(root, ["view_1.png", "view_2.png", "view_4.png"])
    return (ColmapScene(root=str(root), holdout=2, n_val=1), bare, f"{model}: image 3: its name",
            str(root / "images" / bare))


NAMING = [("nerfstudio", "file_path"), ("nerfstudio", "mask_path"), ("nerfstudio", "ply_file_path"),
          ("blender", "file_path"), ("colmap", "name")]


@pytest.mark.parametrize("problem", UNNAMEABLE)
@pytest.mark.parametrize(("form", "key"), NAMING, ids=[f"{form}-{key}" for form, key in NAMING])
def test_a_file_path_no_file_can_have_is_one_line_naming_the_file_and_frame(tmp_path, form, key, problem):
    scene, name, where, named_by = {"nerfstudio": nerfstudio_naming, "blender": blender_naming,
                                    "colmap": colmap_naming}[form](tmp_path, key, UNNAMEABLE[problem])
    with pytest.raises(DatasetError) as caught:
        RayDataModule(scene, batch_rays=64).setup("fit")
        scene.ray_bounds()  # reads the sparse points' file, where 'ply_file_path' names one
    message = str(caught.value)
    if form == "colmap" and problem == "a lone surrogate":
        error = pytest.raises(UnicodeDecodeError, name.encode("utf-8", "surrogatepass").decode).value
        assert message == f"{where} is not UTF-8 text ({error.reason} at byte {error.start})"
    elif (reason := parsed_reason(name)) is not None:
        assert message == f"{where} {reason}, got {name!r:.80}"
    else:
        assert message.endswith(f": cannot be looked up (File name too long) (named by {named_by})"), message[-300:]
    assert "\n" not in message and "\0" not in message
