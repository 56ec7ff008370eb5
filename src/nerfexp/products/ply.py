"""The PLY format (Stanford polygon files), binary little-endian: the meshes and point clouds that MeshLab,
Blender, Open3D and CloudCompare read.

A file is an ASCII header, then each element's rows packed in binary, element after element:

    ply
    format binary_little_endian 1.0
    comment ...
    element vertex V
    property float x            (one line per property, in the order of the row's bytes)
    ...
    element face F
    property list uchar int vertex_indices
    end_header

Here an element is a numpy structured array [N]: a scalar field is a property (``<f4`` is ``float``,
``u1`` is ``uchar``), a field of shape (k,) a list of k values, stored as a ``uchar`` count (k) and
then the k values. ``vertex_rows`` and ``face_rows`` make the elements with the property names readers
look for (``x``, ``nx``, ``red``, ``vertex_indices``).
"""

from collections.abc import Sequence

import numpy as np

PLY_TYPES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
             "f4": "float", "f8": "double"}  # numpy's type codes (without byte order) -> PLY's names


def _ply_type(dtype: np.dtype, field: str) -> str:
    code = f"{dtype.kind}{dtype.itemsize}"
    if code not in PLY_TYPES:
        raise ValueError(f"PLY field {field!r}: type {dtype} has no PLY name (expected one of {sorted(PLY_TYPES)})")
    return code


def ply_bytes(elements: dict[str, np.ndarray], comments: Sequence[str] = ()) -> bytes:
    """A binary little-endian PLY file of ``elements`` (name -> structured array [N], in file order) with
    header ``comments`` (one line each; the header is ASCII, so other characters are escaped as
    ``\\xe9``, ``\\u2019``): the header, then each element's rows, little-endian whatever the machine's
    byte order. Example: one red vertex at the origin,
    ``ply_bytes({"vertex": vertex_rows(np.zeros((1, 3)), np.array([[255, 0, 0]], np.uint8))})``."""
    header = ["ply", "format binary_little_endian 1.0"]
    for comment in comments:
        if "\n" in comment or "\r" in comment:
            raise ValueError(f"PLY comment {comment!r}: a comment is one line")
        header.append("comment " + comment.encode("ascii", "backslashreplace").decode("ascii"))
    bodies = []
    for name, rows in elements.items():
        if rows.ndim != 1 or rows.dtype.names is None or not name.isidentifier():
            raise ValueError(f"PLY element {name!r}: expected a one-dimensional structured array and a name "
                             f"without spaces, got {rows.dtype} of shape {rows.shape}")
        header.append(f"element {name} {len(rows)}")
        stored = []  # (field, little-endian type[, list length]) of each value as it lies in the file
        for field in rows.dtype.names:
            base, shape = rows.dtype[field].base, rows.dtype[field].shape
            code = _ply_type(base, field)
            if shape == ():
                header.append(f"property {PLY_TYPES[code]} {field}")
                stored.append((field, f"<{code}"))
            elif len(shape) == 1 and 0 < shape[0] < 256:
                header.append(f"property list uchar {PLY_TYPES[code]} {field}")
                stored += [(f"{field} count", "u1"), (field, f"<{code}", shape)]
            else:
                raise ValueError(f"PLY field {field!r}: expected a scalar or a list of 1 to 255 values, "
                                 f"got shape {shape}")
        packed = np.empty(len(rows), dtype=np.dtype(stored))  # packed: no padding between fields
        for field in rows.dtype.names:
            packed[field] = rows[field]
            if rows.dtype[field].shape:
                packed[f"{field} count"] = rows.dtype[field].shape[0]
        bodies.append(packed.tobytes())
    header.append("end_header")
    return ("\n".join(header) + "\n").encode("ascii") + b"".join(bodies)


def vertex_rows(positions: np.ndarray, colours: np.ndarray, normals: np.ndarray | None = None) -> np.ndarray:
    """The ``vertex`` element of points ``positions`` [N, 3] with 8-bit ``colours`` [N, 3] (uint8) and,
    where given, unit ``normals`` [N, 3]: fields ``x y z`` (float32), ``nx ny nz`` (float32), ``red green
    blue`` (uchar)."""
    if colours.dtype != np.uint8:
        raise ValueError(f"PLY vertex colours: expected uint8, got {colours.dtype}")
    columns = {"x": positions[:, 0], "y": positions[:, 1], "z": positions[:, 2]}
    if normals is not None:
        columns.update(nx=normals[:, 0], ny=normals[:, 1], nz=normals[:, 2])
    columns.update(red=colours[:, 0], green=colours[:, 1], blue=colours[:, 2])
    rows = np.empty(len(positions), dtype=[(name, "u1" if name in ("red", "green", "blue") else "<f4")
                                           for name in columns])
    for name, value in columns.items():
        rows[name] = value
    return rows


def face_rows(faces: np.ndarray) -> np.ndarray:
    """The ``face`` element of triangles ``faces`` [F, 3] (vertex indices, counter-clockwise seen from the
    side the surface faces): the field ``vertex_indices``, a list of 3 ints."""
    rows = np.empty(len(faces), dtype=[("vertex_indices", "<i4", (3,))])
    rows["vertex_indices"] = faces
    return rows
