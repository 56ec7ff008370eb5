"""Surfaces from a density field: the isosurface of densities sampled on a grid over a box (marching
cubes), and the points where rays end at their rendered depths.

Conventions: ``aabb`` [2, 3] is a box (lower corner, upper corner). A grid over it has ``shape`` (X, Y, Z)
points per axis, the first at the lower corner and the last at the upper one, ``grid_spacing`` apart;
point (i, j, k) has the flat index (i Y + j) Z + k, and values sampled on the grid are an array
[X, Y, Z]. A ``Mesh`` is ``vertices`` [V, 3] in world units, ``faces`` [F, 3] (vertex indices,
counter-clockwise seen from outside) and unit ``normals`` [V, 3] pointing outward, from high values to
low ones.
"""

from typing import NamedTuple

import numpy as np
import torch
from skimage.measure import marching_cubes
from torch import Tensor


class Mesh(NamedTuple):
    """A triangle mesh (see the module's conventions)."""

    vertices: np.ndarray  # [V, 3] float64, world units
    faces: np.ndarray  # [F, 3] int, indices into vertices
    normals: np.ndarray  # [V, 3] float64, unit, outward; zero where the values' gradient vanishes


def grid_shape(aabb: Tensor, resolution: int) -> tuple[int, int, int]:
    """Points per axis (X, Y, Z) of a grid over ``aabb`` [2, 3] with ``resolution`` cells along the box's
    longest edge and cells as near to cubes as the other edges allow: round(edge / h) cells on each edge
    (at least one), h = longest edge / resolution, and one point more than cells.
    Example: a box 2 x 1 x 0.2 at resolution 8 has 8, 4 and 1 cells: shape (9, 5, 2)."""
    edges = (aabb[1] - aabb[0]).double()
    cells = torch.round(edges / edges.max() * resolution).clamp_min(1).long()
    return tuple((cells + 1).tolist())


def grid_spacing(aabb: Tensor, shape: tuple[int, int, int]) -> Tensor:
    """[3] float64: the distance between neighbouring points of the grid ``shape`` over ``aabb`` along each
    axis, (upper - lower) / (points - 1), so that the grid spans the box exactly."""
    return (aabb[1] - aabb[0]).double() / (torch.tensor(shape, dtype=torch.float64) - 1)


def grid_points(aabb: Tensor, shape: tuple[int, int, int], indices: Tensor) -> Tensor:
    """The points [N, 3] (float64) of the grid ``shape`` over ``aabb`` at flat ``indices`` [N] (int64):
    lower + (i, j, k) spacing. A grid is evaluated a slice of indices at a time, so no array of all its
    points is ever made."""
    _, Y, Z = shape
    ijk = torch.stack([indices // (Y * Z), indices // Z % Y, indices % Z], -1)  # [N, 3]
    return aabb[0].double() + ijk.double() * grid_spacing(aabb, shape)


def isosurface(values: np.ndarray, level: float, aabb: Tensor) -> Mesh:
    """The surface where ``values`` [X, Y, Z], sampled on the grid over ``aabb`` (the module's
    conventions), cross ``level``: marching cubes (Lewiner et al. 2003, ``skimage.measure.marching_cubes``)
    puts a vertex on each grid edge whose ends lie on either side of ``level``, where the line between
    their values crosses it; the faces turn counter-clockwise seen from outside, the values above
    ``level`` being inside, and none has zero area (a vertex that falls on a grid point is shared). The normals
    are the values' gradient (converted from grid steps to world units: divided by the spacing),
    pointing down it. A ValueError where no value lies above ``level`` or none at or below it.

    Example: values 1 inside a ball and 0 outside, ``level`` 0.5: vertices half-way along the edges that
    cross the ball's boundary, each within half a cell of it; normals pointing away from the centre."""
    low, high = float(values.min()), float(values.max())
    if not low <= level < high:
        raise ValueError(f"no surface at level {level:g}: the values lie in [{low:g}, {high:g}]")
    spacing = grid_spacing(aabb, values.shape).numpy()
    vertices, faces, gradients, _ = marching_cubes(values, level, spacing=tuple(spacing),
                                                   gradient_direction="descent", allow_degenerate=False)
    # "descent" (the values above level are the object) orders each triangle by the left-hand rule,
    # clockwise seen from outside; reversed here to the right-hand rule that mesh viewers take as facing out
    faces = np.ascontiguousarray(faces[:, ::-1])
    normals = gradients / spacing  # per grid step -> per world unit
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    normals = normals / np.maximum(length, np.finfo(normals.dtype).tiny)  # a zero gradient stays zero
    return Mesh(vertices.astype(np.float64) + aabb[0].double().numpy(), faces, normals.astype(np.float64))


def ray_points(origins: Tensor, directions: Tensor, depth: Tensor) -> Tensor:
    """Where rays o + t d (``origins``, ``directions`` [..., 3]) are at t = ``depth`` [...]: o + depth d
    [..., 3]. The renderer's depth is in units of t (the expected t at which the absorbed light stopped,
    ``nerfexp.nerf.quadrature.composite``); along the unit directions of camera rays
    (``nerfexp.geometry.cameras``) that is a distance along the ray, not a z in the camera's frame."""
    return origins + depth[..., None] * directions
