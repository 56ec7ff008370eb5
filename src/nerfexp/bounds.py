"""The box a scene lives in, ``aabb`` [2, 3] (lower corner, upper corner), for the occupancy grid.

Where it comes from, first match wins (``scene_aabb``): ``data.aabb`` set in the config; the scene's own
``bounding_box()`` (the built-in scene: its objects' extent; Blender scenes: [-1.5, 1.5]^3; LLFF in NDC:
the NDC cube); else the box of everything the training cameras see between ``near`` and ``far``.
"""

import math

import torch
from torch import Tensor

from nerfexp.cameras import pixel_directions
from nerfexp.data.views import Views
from nerfexp.errors import ConfigError

FRUSTUM_SAMPLES = 33  # directions per image side when bounding the cameras' frusta


def parse_aabb(value, key: str = "data.aabb") -> Tensor:
    """``[[x0, y0, z0], [x1, y1, z1]]`` (or the flat ``[x0, y0, z0, x1, y1, z1]``) as a float32 tensor
    [2, 3] with finite x0 < x1, y0 < y1, z0 < z1; anything else is a ConfigError naming ``key``."""
    try:
        box = torch.as_tensor([float(v) for v in _flatten(value)], dtype=torch.float32)
    except (TypeError, ValueError):
        box = None
    if box is None or box.numel() != 6 or not torch.isfinite(box).all() or not (box[:3] < box[3:]).all():
        raise ConfigError(f"{key}: expected the scene's box as [[x0, y0, z0], [x1, y1, z1]] with finite "
                          f"x0 < x1, y0 < y1, z0 < z1 (or null: from the scene or its cameras), got {value!r}")
    return box.reshape(2, 3)


def _flatten(value) -> list:
    if isinstance(value, str | bytes) or not hasattr(value, "__iter__"):
        raise TypeError(value)
    flat = []
    for item in value:
        flat += _flatten(item) if hasattr(item, "__iter__") and not isinstance(item, str) else [item]
    return flat


def frustum_aabb(views: Views, near: float, far: float) -> Tensor:
    """The box [2, 3] of all points o + t d, t in [near, far], that the cameras ``views`` see (d unit).

    Bounded from ``FRUSTUM_SAMPLES``^2 directions per image, the borders included, at near and far, and
    padded by far (1 - cos(h / 2)) on every side, h the largest angle between neighbouring samples: no
    point of a frustum lies farther than that outside the sampled points' box.
    """
    d_cam = pixel_directions(views.height, views.width, views.focal, dtype=torch.float64)  # [H, W, 3]
    rows = torch.linspace(0, views.height - 1, FRUSTUM_SAMPLES).round().long()
    cols = torch.linspace(0, views.width - 1, FRUSTUM_SAMPLES).round().long()
    d = d_cam[rows][:, cols].reshape(-1, 3)
    d = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)
    c2w = views.c2w.to(torch.float64)
    world = torch.einsum("nij,kj->nki", c2w[:, :3, :3], d)  # [N, K, 3]
    points = torch.cat([c2w[:, None, :3, 3] + t * world for t in (near, far)], 1).reshape(-1, 3)
    spacing = max(math.atan(views.width / views.focal / 2), math.atan(views.height / views.focal / 2))
    spacing = 2 * spacing / (FRUSTUM_SAMPLES - 1) * math.sqrt(2)  # the diagonal between neighbours
    pad = far * (1 - math.cos(spacing / 2))
    return torch.stack([points.amin(0) - pad, points.amax(0) + pad]).float()


def scene_aabb(scene, train_views: Views | None, near: float, far: float) -> Tensor:
    """The box [2, 3] of ``scene``: its ``bounding_box()`` (which honours ``data.aabb``) where it has
    one (and it is not None), else the box its training cameras ``train_views`` see between ``near`` and ``far``."""
    explicit = getattr(scene, "aabb", None)
    if explicit is not None:
        return parse_aabb(explicit)
    own = getattr(scene, "bounding_box", None)
    box = own() if own is not None else None
    if box is not None:
        return box
    if train_views is None:
        raise ConfigError("the scene has no bounding box and no training views to bound: set data.aabb")
    return frustum_aabb(train_views, near, far)
