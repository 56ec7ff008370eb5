"""Image files, transforms files and poses_bounds.npy that are damaged or hostile: each either loads
exactly what it holds or is a one-line DatasetError naming the file, never a traceback of another kind
and never wrong values. The fuzz tests generate the inputs (hypothesis)."""

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

from nerfexp.data.blender import load_blender
from nerfexp.data.images import MAX_PIXELS, read_image
from nerfexp.data.llff import read_poses_bounds
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
