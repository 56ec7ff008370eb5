"""Scene contraction for unbounded scenes (mip-NeRF 360, Barron et al., CVPR 2022, eq. 10; nerfstudio's
``SceneContraction``): the fields see every position of an unbounded world inside a bounded box, the inner
region unchanged and all that lies beyond it squeezed towards a shell, so that a room's walls or a sky get a
background instead of clamped far samples.

Conventions: ``x`` are positions in the inner region's units, [..., 3] (the world's, moved by ``centre`` and
divided by ``radius``); ``norm`` is "l2" (mip-NeRF 360's ball) or "linf" (nerfacto's box with the hash grid).
With |x| that norm::

    contract(x) = x                          |x| <= 1
                = (2 - 1 / |x|) x / |x|      |x| > 1

so contracted points lie in the ball (or cube) of radius 2. The map is continuous with a continuous first
derivative at |x| = 1 (there the outer branch's Jacobian is the identity), and finite for any finite or
infinite x: the direction x / |x| is taken after dividing by the largest coordinate, and an infinite
coordinate gives the direction of the infinite part.
"""

from collections.abc import Sequence
from typing import ClassVar

import torch
from torch import Tensor, nn

from nerfexp.domains import POSITION, POSITION_LIMIT, Applies, Rule, choice, list_of, optional, real

NORMS = ("l2", "linf")
CONTRACTED_RADIUS = 2.0  # every contracted point lies within this of the origin (in the chosen norm)


def vector_norm(x: Tensor, norm: str) -> Tensor:
    """|x| [...] of x [..., 3] in ``norm`` ("l2" or "linf")."""
    return torch.linalg.vector_norm(x, ord=2 if norm == "l2" else float("inf"), dim=-1)


def direction_and_norm(x: Tensor, norm: str) -> tuple[Tensor, Tensor]:
    """(x / |x| [..., 3], |x| [...]) without overflow or inf / inf: x is divided by its largest coordinate
    m = max_i |x_i| first (|x / m| is between 1 and sqrt 3); where m is infinite the direction is that of
    the infinite coordinates (their signs) and |x| is inf. Zero vectors get direction 0 and |x| = 0."""
    m = x.abs().amax(-1, keepdim=True)  # [..., 1]
    infinite = torch.isinf(m)
    safe_m = torch.where((m == 0) | infinite, 1, m)
    scaled = torch.where(infinite, torch.where(torch.isinf(x), torch.sign(x), 0), x / safe_m)  # [..., 3]
    scaled_norm = vector_norm(scaled, norm)[..., None]
    direction = scaled / torch.where(scaled_norm == 0, 1, scaled_norm)
    return direction, (m * scaled_norm).squeeze(-1)


def contract(x: Tensor, norm: str = "l2") -> Tensor:
    """mip-NeRF 360's contraction of positions x [..., 3] (see the module docstring) -> [..., 3], each within
    ``CONTRACTED_RADIUS`` of the origin in ``norm``.

    The outer branch is evaluated only at |x| >= 1 (its input clamped there), so its gradient is finite
    wherever it is not selected (the inner points' gradient is the identity).

    >>> contract(torch.tensor([[0.5, 0, 0], [2.0, 0, 0], [float("inf"), 1, 0]]))
    tensor([[0.5000, 0.0000, 0.0000],
            [1.5000, 0.0000, 0.0000],
            [2.0000, 0.0000, 0.0000]])
    """
    direction, length = direction_and_norm(x, norm)
    inside = length <= 1
    outer_length = torch.where(inside, 1, length)  # >= 1: 1 / |x| is finite, 0 at inf
    outer = (2 - 1 / outer_length)[..., None] * direction
    return torch.where(inside[..., None], x, outer)


def stretch(contracted: Tensor, norm: str = "l2") -> Tensor:
    """How many world units (inner-region units) one contracted unit spans at most, around contracted points
    [..., 3]: [...], 1 inside the unit ball, r^2 outside it, where r = 1 / (2 - |c|) is the world distance of a
    contracted point at |c| (the radial derivative dr/d|c| = r^2 exceeds the tangential one, r / |c|), inf on
    the shell |c| = 2. The occupancy grid measures its cells' sizes in world units with it."""
    length = vector_norm(contracted, norm)
    world = 1 / (CONTRACTED_RADIUS - length).clamp_min(0)  # inf at the shell (1 / 0 = inf, never nan)
    return torch.where(length <= 1, 1, world.square())


class SceneContraction(nn.Module):
    """The contraction axis's component (``contraction=mipnerf360``): positions [..., 3] in the world ->
    contracted positions [..., 3] in the box ``box`` = [-2, 2]^3, which the fields, the hash grid and the
    occupancy grid work in.

    Rays end ``far`` inner-region radii from their origin (``far_distance``; nerfacto's 1000, its scenes scaled
    to a radius of 1): the scene format's far bound, made for bounded scenes, is not read.

    The inner region is the ball (``norm`` "l2") or cube ("linf") of ``radius`` around ``centre``: by default
    (both None) the smallest around the training cameras' centroid that holds every camera centre (mip-NeRF
    360 scales its scenes so), set once when training starts (``NeRFModule.on_train_start`` calls
    ``set_inner``) and saved in checkpoints. Beyond it, samples are spaced evenly in disparity
    (``ray_split``: where each ray leaves the inner region).
    """

    DOMAINS: ClassVar[dict[str, Rule]] = {
        "norm": choice(*NORMS),
        # a point and a distance in scene units: within POSITION_LIMIT, where float32 positions still resolve a unit
        "centre": optional(list_of(POSITION, 3), "the training cameras' centroid"),
        "radius": optional(real(0, POSITION_LIMIT, above=True), "the farthest training camera from the centre"),
        "far": real(1, 2 ** 24, above=True),
    }
    APPLIES: ClassVar[dict[str, Applies]] = {}
    # the scene's settings it takes the place of: the grids work in its box, and rays end at its own far
    REPLACES_SCENE: ClassVar[dict[str, str]] = {
        "aabb": "contraction=mipnerf360 (the grids work in the contraction's box, [-2, 2]^3)",
        "far": "contraction=mipnerf360 (rays end contraction.function.far radii away)",
    }

    @staticmethod
    def WORLD_RAYS(ndc: str, world: str) -> str:
        """It contracts world positions: refused with NDC rays (``ndc``; ``world``: how to have world rays)."""
        return (f"contraction=mipnerf360 and {ndc}: NDC rays already bound a forward-facing scene's depth; set "
                f"{world} to contract world positions, or contraction=none")

    def __init__(self, norm: str = "l2", centre: Sequence[float] | None = None, radius: float | None = None,
                 far: float = 1000.0):
        super().__init__()
        if norm not in NORMS:
            raise ValueError(f"contraction.function.norm: expected one of {list(NORMS)}, got {norm!r}")
        if not far > 1:
            raise ValueError(f"contraction.function.far: expected a number of inner-region radii > 1, got {far}")
        self.norm = norm
        self.far = far
        self.register_buffer("centre", torch.full((3,), torch.nan, dtype=torch.float64))
        self.register_buffer("radius", torch.tensor(torch.nan, dtype=torch.float64))
        self._fixed = {"centre": centre, "radius": radius}
        self.register_load_state_dict_post_hook(SceneContraction._after_load)
        self._set = False
        if centre is not None and radius is not None:
            self.set_inner(torch.tensor(centre, dtype=torch.float64), float(radius))

    @staticmethod
    def _after_load(module: "SceneContraction", incompatible_keys) -> None:
        module._set = bool(torch.isfinite(module.centre).all() and torch.isfinite(module.radius))

    @property
    def has_inner(self) -> bool:
        """Whether the inner region is set (known on the host)."""
        return self._set

    def set_inner(self, centre: Tensor, radius: float) -> None:
        """Set the inner region: ``centre`` [3] and ``radius`` > 0, in world units; the values the config
        fixed (``contraction.function.centre``, ``radius``) win over those given."""
        if self._fixed["centre"] is not None:
            centre = torch.tensor(self._fixed["centre"], dtype=torch.float64)
        if self._fixed["radius"] is not None:
            radius = float(self._fixed["radius"])
        if centre.shape != (3,) or not torch.isfinite(centre).all() or not 0 < radius < float("inf"):
            raise ValueError(f"SceneContraction: expected a finite centre [3] and a radius > 0, got "
                             f"{centre.tolist()} and {radius}")
        self.centre.copy_(centre)
        self.radius.fill_(radius)
        self._set = True

    @property
    def box(self) -> Tensor:
        """The box [2, 3] that contracted positions lie in: [-2, 2]^3."""
        return torch.tensor([[-CONTRACTED_RADIUS] * 3, [CONTRACTED_RADIUS] * 3])

    @property
    def far_distance(self) -> float:
        """Where rays end, in world units: ``far`` times the inner region's radius."""
        if not self._set:
            raise RuntimeError("SceneContraction has no inner region yet: its far distance follows its radius")
        return self.far * float(self.radius)

    def inner(self, points: Tensor) -> Tensor:
        """World positions [..., 3] in the inner region's units: (points - centre) / radius."""
        if not self._set:
            raise RuntimeError("SceneContraction has no inner region: set contraction.function.centre and "
                               "radius, or train (the module sets them from the training cameras)")
        return (points - self.centre.to(points.dtype)) / self.radius.to(points.dtype)

    def forward(self, points: Tensor) -> Tensor:
        """World positions [..., 3] -> contracted positions [..., 3] in ``box``."""
        return contract(self.inner(points), self.norm)

    def stretch(self, contracted: Tensor) -> Tensor:
        """World units per contracted unit around contracted points [..., 3] (``stretch``, times the radius)."""
        return stretch(contracted, self.norm) * self.radius.to(contracted.dtype)

    def ray_split(self, origins: Tensor, directions: Tensor) -> Tensor:
        """Where each ray o + t d (``origins``, ``directions`` [B, 3]) leaves the inner region: t [B] (0 for a
        ray that starts outside it). For the ball, the larger root of |o' + t d'| = 1 in the inner units; for the
        cube, the nearest exit face."""
        o, d = self.inner(origins), directions / self.radius.to(directions.dtype)
        if self.norm == "l2":
            a = (d * d).sum(-1)
            b = (o * d).sum(-1)
            c = (o * o).sum(-1) - 1
            # t = (-b + sqrt(b^2 - a c)) / a; for c <= 0 (inside) the discriminant is >= b^2 >= 0. Written as
            # -c / (b + sqrt(...)) where b > 0 to avoid cancelling two nearly equal numbers.
            root = torch.sqrt((b * b - a * c).clamp_min(0))
            t = torch.where(b > 0, -c / torch.where(b + root == 0, 1, b + root), (root - b) / a)
            t = torch.where(c > 0, 0, t)  # starts outside the ball
        else:
            bound = torch.where(d > 0, 1 - o, -1 - o)  # the face each coordinate runs towards
            moving = d != 0
            t = torch.where(moving, bound / torch.where(moving, d, 1), torch.inf).amin(-1)
        return t.clamp_min(0)
