"""A capture's sparse points (structure from motion's 3D points) and the ray bounds they give.

``near_far``: the ray bounds from the points each image sees (LLFF's percentiles, as COLMAP scenes and
nerfstudio captures with points use them). ``read_ply_points``: the vertices x, y, z of a PLY file (ASCII or
binary, as nerfstudio's ``ns-process-data`` writes COLMAP's points to ``sparse_pc.ply``), read strictly: a file
that is not such a PLY is a DatasetError naming it.
"""

from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from nerfexp.domains import POSITION_LIMIT
from nerfexp.errors import DatasetError
from nerfexp.reading import UnreadableFile, read_bytes

PERCENTILES = (0.1, 99.9)  # of each image's point distances: near and far (as LLFF's imgs2poses)
MARGINS = (0.9, 1.1)  # near and far are widened by these factors
PLY_MAX_BYTES = 1 << 30  # a sparse point cloud of tens of millions of points
PLY_SCALARS = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
               "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
               "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}  # PLY's type names -> numpy's
PLY_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


def near_far(centres: Tensor, points: Tensor, observed: list[Tensor]) -> tuple[float, float] | None:
    """Ray bounds from sparse points: centres [N, 3], points [P, 3], observed[i] the indices [K_i] of the
    points image i sees. near = 0.9 min_i q0.1_i, far = 1.1 max_i q99.9_i, with q_i the percentiles of
    image i's distances |X - c_i| (images that see no point are left out); None where no image sees a point."""
    low, high = [], []
    for centre, index in zip(centres, observed):
        if len(index):
            distances = torch.linalg.vector_norm(points[index] - centre, dim=-1)
            q = torch.quantile(distances, torch.tensor(PERCENTILES, dtype=distances.dtype) / 100)
            low.append(q[0])
            high.append(q[1])
    if not low:
        return None
    return MARGINS[0] * torch.stack(low).min().item(), MARGINS[1] * torch.stack(high).max().item()


def read_ply_points(path: Path) -> Tensor:
    """The vertices' positions [P, 3] float64 of the PLY file ``path``: the ``vertex`` element's ``x``, ``y``,
    ``z`` (any scalar type, other scalar properties skipped), in the ASCII or either binary format. The vertex
    element must come first and hold no list property (as point clouds are written); elements after it are not
    read. Anything else, a short or damaged file, or a position not finite or beyond 2^24, is a DatasetError
    naming the file."""
    try:
        data = read_bytes(path, PLY_MAX_BYTES)
    except UnreadableFile as error:
        raise DatasetError(str(error)) from None
    end = data.find(b"end_header")
    body_start = data.find(b"\n", end) + 1 if end >= 0 else 0
    if not data.startswith(b"ply") or end < 0 or body_start == 0:
        raise DatasetError(f"{path}: not a PLY file (expected 'ply' on the first line and an 'end_header' line)")
    lines = [line.strip().split() for line in data[:end].decode("ascii", "replace").splitlines()[1:]]
    lines = [line for line in lines if line and line[0] not in ("comment", "obj_info")]
    fmt = lines[0][1] if lines and lines[0][0] == "format" and len(lines[0]) == 3 else None
    if fmt not in PLY_FORMATS:
        raise DatasetError(f"{path}: expected 'format ascii 1.0', 'format binary_little_endian 1.0' or "
                           f"'format binary_big_endian 1.0' after 'ply', got {' '.join(lines[0]) if lines else ''!r}")
    if len(lines) < 2 or lines[1][:2] != ["element", "vertex"] or len(lines[1]) != 3 or not lines[1][2].isdigit():
        raise DatasetError(f"{path}: expected the first element to be 'element vertex COUNT' (a point cloud)")
    count, properties = int(lines[1][2]), []
    for line in lines[2:]:
        if line[0] != "property":
            break
        if len(line) != 3 or line[1] not in PLY_SCALARS:
            raise DatasetError(f"{path}: vertex property {' '.join(line[1:])!r} is not a scalar PLY type "
                               f"({', '.join(sorted(set(PLY_SCALARS)))}); nerfexp reads point clouds")
        properties.append((line[2], PLY_SCALARS[line[1]]))
    names = [name for name, _ in properties]
    if not {"x", "y", "z"} <= set(names) or len(set(names)) != len(names):
        raise DatasetError(f"{path}: the vertex element must have the properties x, y and z once each, got "
                           f"{', '.join(names) or 'none'}")
    body = data[body_start:]
    try:
        if count == 0:
            xyz = np.zeros((0, 3))
        elif PLY_FORMATS[fmt] is None:
            rows = np.loadtxt(body.decode("ascii").splitlines()[:count], dtype=np.float64, ndmin=2)
            if rows.shape != (count, len(names)):
                raise ValueError(f"{rows.shape[0]} rows of {rows.shape[1] if rows.ndim == 2 else 0} values")
            xyz = rows[:, [names.index(axis) for axis in "xyz"]]
        else:
            dtype = np.dtype([(name, PLY_FORMATS[fmt] + code) for name, code in properties])
            if len(body) < count * dtype.itemsize:
                raise ValueError(f"{len(body)} bytes where {count} vertices take {count * dtype.itemsize}")
            rows = np.frombuffer(body, dtype=dtype, count=count)
            xyz = np.stack([rows[axis].astype(np.float64) for axis in "xyz"], -1).reshape(count, 3)
    except (ValueError, UnicodeDecodeError) as error:
        raise DatasetError(f"{path}: the vertex data do not match the header's {count} vertices ({error})") from None
    points = torch.from_numpy(np.ascontiguousarray(xyz))
    if not bool((points.abs() <= POSITION_LIMIT).all()):  # NaN is not
        raise DatasetError(f"{path}: a point that is not finite or lies more than 2^24 scene units from the origin")
    return points
