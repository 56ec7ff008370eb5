"""PLY files (``nerfexp.products.ply``) read back by an independent reader: the header parsed line by line, each
element's rows by ``numpy.frombuffer`` with a dtype built from the header, and one file against bytes
packed by hand with ``struct``."""

import struct

import numpy as np
import pytest

from nerfexp.products.ply import face_rows, ply_bytes, vertex_rows
from tests.helpers import read_ply


def test_one_vertex_is_the_bytes_the_ply_specification_gives():
    positions = np.array([[1.0, -2.5, 3.25]])
    data = ply_bytes({"vertex": vertex_rows(positions, np.array([[255, 0, 7]], np.uint8))}, ["made by hand"])
    header = ("ply\nformat binary_little_endian 1.0\ncomment made by hand\nelement vertex 1\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    assert data == header.encode("ascii") + struct.pack("<fffBBB", 1.0, -2.5, 3.25, 255, 0, 7)


def test_a_mesh_reads_back_with_its_counts_types_and_values():
    rng = np.random.default_rng(0)
    positions = rng.normal(size=(5, 3))
    normals = positions / np.linalg.norm(positions, axis=1, keepdims=True)
    colours = rng.integers(0, 256, (5, 3), dtype=np.uint8)
    faces = np.array([[0, 1, 2], [2, 3, 4], [4, 1, 0]])
    data = ply_bytes({"vertex": vertex_rows(positions, colours, normals), "face": face_rows(faces)},
                     ["first", "caf\u00e9"])
    comments, elements = read_ply(data)
    assert comments == ["first", "caf\\xe9"]  # the header is ASCII
    vertex, face = elements["vertex"], elements["face"]
    assert len(vertex) == 5 and len(face) == 3
    assert vertex.dtype.names == ("x", "y", "z", "nx", "ny", "nz", "red", "green", "blue")
    assert [vertex.dtype[n].str for n in ("x", "nx", "red")] == ["<f4", "<f4", "|u1"]
    xyz = np.stack([vertex[n] for n in ("x", "y", "z")], 1)
    assert np.array_equal(xyz, positions.astype(np.float32))
    assert np.array_equal(np.stack([vertex[n] for n in ("nx", "ny", "nz")], 1), normals.astype(np.float32))
    assert np.array_equal(np.stack([vertex[n] for n in ("red", "green", "blue")], 1), colours)
    assert face.dtype["vertex_indices"].base.str == "<i4" and np.array_equal(face["vertex_indices"], faces)


def test_an_empty_point_cloud_is_a_header_with_no_rows():
    data = ply_bytes({"vertex": vertex_rows(np.zeros((0, 3)), np.zeros((0, 3), np.uint8))})
    assert data.endswith(b"element vertex 0\nproperty float x\nproperty float y\nproperty float z\n"
                         b"property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    assert len(read_ply(data)[1]["vertex"]) == 0


def test_big_endian_arrays_are_written_little_endian():
    rows = np.array([(1.5, 258)], dtype=[("x", ">f8"), ("count", ">u2")])
    data = ply_bytes({"thing": rows})
    assert data.endswith(b"property double x\nproperty ushort count\nend_header\n" + struct.pack("<dH", 1.5, 258))


@pytest.mark.parametrize("elements, comments, message", [
    ({"vertex": np.zeros(2, dtype=[("x", "<f2")])}, [], "type float16 has no PLY name"),
    ({"vertex": np.zeros(2, dtype=[("x", "<f4", (2, 2))])}, [], "a scalar or a list"),
    ({"two words": np.zeros(2, dtype=[("x", "<f4")])}, [], "a name without spaces"),
    ({"vertex": np.zeros(2)}, [], "structured array"),
    ({}, ["two\nlines"], "a comment is one line"),
])
def test_what_ply_cannot_hold_is_a_value_error_naming_it(elements, comments, message):
    with pytest.raises(ValueError, match=message):
        ply_bytes(elements, comments)


def test_vertex_colours_must_be_8_bit():
    with pytest.raises(ValueError, match="expected uint8"):
        vertex_rows(np.zeros((1, 3)), np.zeros((1, 3)))
