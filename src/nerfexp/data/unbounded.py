"""The built-in still life inside a room: ground truth for unbounded scenes (``nerfexp-scene --scene unbounded``).

The objects of ``nerfexp.data.procedural`` (within ``SCENE_RADIUS`` of the origin, cameras at ``CAMERA_RADIUS``)
stand inside an opaque sphere of radius ``ROOM_RADIUS``, ten times the cameras' distance: its inside is painted
with a latitude/longitude checker over a floor-to-ceiling gradient, and lit evenly (its colour does not depend on
the view). Every ray ends somewhere, so every pixel is opaque, and what lies behind the objects is far outside
the ball that holds the cameras: a renderer bounded by the objects' far plane shows its background colour
there, and one that contracts the world sees the room (``contraction=mipnerf360``).
"""

import math

import torch
from torch import Tensor

from nerfexp.data.procedural import load_procedural, trace
from nerfexp.data.views import Views
from nerfexp.geometry.lenses import Intrinsics

ROOM_RADIUS = 40.0  # ten times procedural.CAMERA_RADIUS
ROOM_CELLS = (24, 12)  # checker cells around the horizon and from floor to ceiling
ROOM_COLOURS = ((0.85, 0.55, 0.35), (0.35, 0.45, 0.6))  # the checker's two paints
FLOOR, CEILING = (0.45, 0.35, 0.25), (0.95, 0.95, 0.9)  # the gradient's ends, multiplied into the checker


def leave_sphere(origins: Tensor, directions: Tensor, radius: float) -> Tensor:
    """Distance t [...] at which rays from inside the sphere |x| = radius (unit ``directions``) leave it: the
    larger root of |o + t d| = radius, t = -b + sqrt(b^2 - c) with b = d.o, c = |o|^2 - r^2 < 0 (so the square
    root is real and at least |b|)."""
    b = (directions * origins).sum(-1)
    c = (origins * origins).sum(-1) - radius**2
    return -b + torch.sqrt(b * b - c)


def room_colour(points: Tensor) -> Tensor:
    """The room's colour [..., 3] at points [..., 3] on its wall: the checker of ``ROOM_COLOURS`` by longitude
    and latitude, times the gradient from ``FLOOR`` (bottom) to ``CEILING`` (top)."""
    x, y, z = points.unbind(-1)
    longitude = torch.atan2(y, x) + math.pi  # [0, 2 pi]
    latitude = torch.acos((z / ROOM_RADIUS).clamp(-1, 1))  # [0, pi], 0 at the ceiling
    cells = torch.stack([longitude / (2 * math.pi) * ROOM_CELLS[0], latitude / math.pi * ROOM_CELLS[1]], -1)
    odd = (torch.floor(cells).sum(-1) % 2)[..., None]
    first, second = (torch.tensor(c, dtype=points.dtype) for c in ROOM_COLOURS)
    height = (1 - latitude / math.pi)[..., None]  # 1 at the ceiling
    gradient = torch.lerp(torch.tensor(FLOOR, dtype=points.dtype), torch.tensor(CEILING, dtype=points.dtype), height)
    return (first + odd * (second - first)) * gradient


def trace_unbounded(origins: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
    """Colour [..., 3] and hit mask [...] (all true) of rays from inside the room: the still life where a ray
    meets it (``procedural.trace``), else the room's wall."""
    rgb, hit = trace(origins, directions)
    wall = origins + leave_sphere(origins, directions, ROOM_RADIUS)[..., None] * directions
    return torch.where(hit[..., None], rgb, room_colour(wall)), torch.ones_like(hit)


def load_unbounded(split: str, n_views: int, height: int, width: int, supersample: int = 2,
                   lens: Intrinsics | None = None) -> Views:
    """``n_views`` rendered views of ``split`` from the built-in scene's cameras through ``lens`` (None: the
    Blender pinhole), as ``Views``: every pixel opaque."""
    return load_procedural(split, n_views, height, width, supersample, trace_unbounded, lens)
