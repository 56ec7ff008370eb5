"""Normalized device coordinates (NDC) for forward-facing scenes (the NeRF paper's appendix C).

A camera at the origin looking down -z, with focal length ``f`` in pixels and an image of
``H`` x ``W`` pixels, sees the frustum z <= -near; the perspective projection

    pi(x, y, z) = (-(f / (W/2)) x / z,  -(f / (H/2)) y / z,  1 + 2 near / z)

maps it to the cube [-1, 1]^3: the image's edges to x, y = +-1, the near plane z = -near to
z' = -1 and infinity to z' = 1. Straight lines stay straight, so a ray o + t d becomes the ray
o' + t' d' with t' in [0, 1) spanning near to infinity, and samples evenly spaced in t' are
evenly spaced in disparity 1 / z: the whole unbounded depth range of a forward-facing capture is
covered by a finite interval.

Naming: ``origins``, ``directions`` [..., 3] are world rays (any length of direction); the
results are NDC rays whose directions are not unit vectors.
"""

import torch
from torch import Tensor


def ndc_points(points: Tensor, focal: float, height: int, width: int, near: float) -> Tensor:
    """The projection pi of points [..., 3] (z < 0) into NDC: [..., 3] (formula in the module docstring)."""
    x, y, z = points.unbind(-1)
    return torch.stack([-(2 * focal / width) * x / z, -(2 * focal / height) * y / z, 1 + 2 * near / z], -1)


def ndc_rays(origins: Tensor, directions: Tensor, focal: float, height: int, width: int,
             near: float) -> tuple[Tensor, Tensor]:
    """World rays [..., 3] -> NDC rays (origins_ndc, directions_ndc), each [..., 3].

    Each ray is first moved along itself to the near plane: o_n = o + t_n d with
    t_n = -(near + o_z) / d_z, so o_n,z = -near. With a = 2 f / W, b = 2 f / H, the point
    o_n + t d projects to pi(o_n) + t' d' where

        o'  = pi(o_n) = (-a o_x / o_z, -b o_y / o_z, 1 + 2 near / o_z)      (o = o_n below)
        d'  = (-a (d_x / d_z - o_x / o_z), -b (d_y / d_z - o_y / o_z), -2 near / o_z)
        t'  = t d_z / (o_z + t d_z) = 1 - o_z / (o_z + t d_z)

    (substitute and simplify each coordinate). Since o_z = -near, o'_z = -1 and d'_z = 2: t' = 0 at
    the near plane and t' -> 1 as t -> infinity.

    Requires rays that look into the frustum: d_z < 0 (every ray of a forward-facing camera whose
    axis is near -z). A ray with d_z = 0 never reaches the near plane and has no NDC form.

    Example: the ray o = (0, 0, 0), d = (0, 0, -1) with near 1 becomes o' = (0, 0, -1), d' = (0, 0, 2).
    """
    t_near = -(near + origins[..., 2]) / directions[..., 2]
    o = origins + t_near[..., None] * directions
    ox, oy, oz = o.unbind(-1)
    dx, dy, dz = directions.unbind(-1)
    a, b = 2 * focal / width, 2 * focal / height
    origins_ndc = ndc_points(o, focal, height, width, near)
    directions_ndc = torch.stack([-a * (dx / dz - ox / oz), -b * (dy / dz - oy / oz), -2 * near / oz], -1)
    return origins_ndc, directions_ndc
