"""Axis-aligned boxes ``aabb`` [2, 3] (lower corner, upper corner): parsed from the config, or bounding
what cameras see. The occupancy grid covers one (``nerfexp.data.base.Scene.box`` chooses which)."""

import math

import torch
from torch import Tensor

from nerfexp.domains import POSITION_LIMIT
from nerfexp.errors import ConfigError
from nerfexp.geometry.lenses import Intrinsics, border_pixels, pixel_rays

FRUSTUM_SAMPLES = 33  # directions per image side when bounding the cameras' frusta


def box_problem(box: Tensor) -> str | None:
    """Why a box [2, 3] is not one an occupancy grid can cover, or None: its corners must be finite, within
    ``POSITION_LIMIT`` of the origin along each axis (float32 positions farther out have no sub-unit
    resolution), and, as float32 (the grid's), lower < upper on every axis (a box without volume holds nothing)."""
    if not bool(torch.isfinite(box).all()):
        return "is not finite"
    if float(box.abs().max()) > POSITION_LIMIT:
        return "reaches more than 2^24 scene units from the origin, where float32 positions have no sub-unit resolution"
    corners = box.float()
    if not bool((corners[0] < corners[1]).all()):
        return "is empty: as float32 its lower corner is not below its upper one on every axis"
    return None


def parse_aabb(value, key: str = "data.aabb") -> Tensor:
    """``[[x0, y0, z0], [x1, y1, z1]]`` (or the flat ``[x0, y0, z0, x1, y1, z1]``) as a float32 tensor
    [2, 3] that an occupancy grid can cover (``box_problem``); anything else is a ConfigError naming ``key``."""
    try:
        box = torch.as_tensor([float(v) for v in _flatten(value)], dtype=torch.float64)
    except (TypeError, ValueError, OverflowError):
        box = None
    if box is None or box.numel() != 6 or box_problem(box.reshape(2, 3)) is not None:
        raise ConfigError(f"{key}: expected the scene's box as [[x0, y0, z0], [x1, y1, z1]] of finite numbers within "
                          f"+-2^24 with x0 < x1, y0 < y1, z0 < z1 (or null: from the scene or its cameras), got "
                          f"{value!r:.200}")
    return box.reshape(2, 3).float()


def _flatten(value) -> list:
    if isinstance(value, str | bytes) or not hasattr(value, "__iter__"):
        raise TypeError(value)
    flat = []
    for item in value:
        flat += _flatten(item) if hasattr(item, "__iter__") and not isinstance(item, str) else [item]
    return flat


def frustum_aabb(c2w: Tensor, intrinsics: Intrinsics, height: int, width: int, near: float, far: float) -> Tensor:
    """The box [2, 3] of all points o + t d, t in [near, far], that cameras ``c2w`` [N, 4, 4] with lenses
    ``intrinsics`` [N] and images of ``height`` x ``width`` pixels see (d unit).

    Bounded from ``FRUSTUM_SAMPLES``^2 directions per image, spread over its whole extent (its corners
    included), at near and far, and padded by far (1 - cos(h / 2)) on every side, h the largest angle
    between diagonal neighbours among the samples: no point of a frustum lies farther than that outside
    the sampled points' box.
    """
    c2w = c2w.to(torch.float64)
    pixels = border_pixels(height, width, FRUSTUM_SAMPLES).reshape(FRUSTUM_SAMPLES, FRUSTUM_SAMPLES, 2)
    d = pixel_rays(pixels, intrinsics.to(torch.float64).unsqueeze(2))  # [N, S, S, 3]
    diagonal = torch.cat([(d[..., 1:, 1:, :] * d[..., :-1, :-1, :]).sum(-1).flatten(),
                          (d[..., 1:, :-1, :] * d[..., :-1, 1:, :]).sum(-1).flatten()])
    spacing = torch.arccos(diagonal.clamp(-1, 1)).max().item()
    world = torch.einsum("nij,nkj->nki", c2w[:, :3, :3], d.reshape(len(c2w), -1, 3))  # [N, K, 3]
    points = torch.cat([c2w[:, None, :3, 3] + t * world for t in (near, far)], 1).reshape(-1, 3)
    pad = far * (1 - math.cos(spacing / 2))
    return torch.stack([points.amin(0) - pad, points.amax(0) + pad]).float()
