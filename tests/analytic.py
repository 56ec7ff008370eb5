"""Density fields whose renders have closed forms: the truth that the renderer's quadrature converges to
(for the tests and ``benchmarks/accuracy/quadrature.py``; nothing of nerfexp uses them).

Conventions (every field here): a ray x(t) = o + t d, with d a unit vector, is rendered over [near, far].
Its transmittance is T(t) = exp(-tau(t)), tau(t) = int_near^t sigma(x(s)) ds, and it terminates at t
with probability density p(t) = sigma T = -dT/dt, so

    opacity = 1 - T(far)
    depth   = E[t | absorbed] = int_near^far t p(t) dt / opacity
            = (near - far T(far) + int_near^far T dt) / (1 - T(far))     (by parts: -int t dT)
            = far - int_near^far (1 - T) dt / (1 - T(far))               (the same, without the cancellation)

A ray that absorbs nothing is reported at depth ``far``, as ``nerfexp.nerf.quadrature.composite`` does.
Each field has one colour c, so a ray's colour is opacity c + (1 - opacity) background, and the field's
``forward`` is the field interface of ``nerfexp.nerf.fields``: positions [..., S, 3] and directions
[..., S or 1, 3] -> (rgb [..., S, 3], sigma [..., S]), in the positions' dtype. Truths are float64.
At the end, what tests and benchmarks need to score a renderer against the truth: rays aimed at a field
(``aimed_rays``; ``rays_down_z``, straight down onto a ``slab``), mean errors (``render_errors``), and the cost
of an accuracy (``cost_for_error``).

Example: a ray down z through the slab |z| < 1/2 of density 3 absorbs 1 - exp(-3) of the light:
>>> slab = Slab(normal=(0.0, 0.0, 1.0), lower=-0.5, upper=0.5, density=3.0)
>>> slab.truth(torch.tensor([[0.0, 0.0, 4.0]]), torch.tensor([[0.0, 0.0, -1.0]]), 2.0, 6.0)["opacity"]
tensor([0.9502], dtype=torch.float64)
"""

import abc
import math

import numpy as np
import torch
from torch import Tensor, nn

from nerfexp.nerf.fields import FieldOutputs, PositionalOutputs


def segments_truth(starts: Tensor, ends: Tensor, density: float, near: float, far: float) -> tuple[Tensor, Tensor]:
    """Exact opacity and depth [B] of rays that cross density ``density`` on segments [starts, ends] [B, K].

    Segments are sorted along each ray and disjoint; they may reach beyond [near, far] (infinite ends
    too) and are clipped to it here; an empty segment has ends <= starts. In segment k, [a_k, b_k] after
    clipping, of length L_k and optical depth tau_k = s L_k, entered with T_k = exp(-sum_{j<k} tau_j),
    the ray stops with probability T_k alpha_k, alpha_k = 1 - exp(-tau_k), at a_k plus an exponential
    distance of rate s truncated at L_k:

        opacity = sum_k T_k alpha_k = 1 - exp(-sum_k tau_k)
        depth   = sum_k T_k (a_k alpha_k + L_k g(tau_k)) / opacity,   g(tau) = alpha / tau - exp(-tau)

    since int_0^L t s exp(-s t) dt = L g(s L). g(tau) -> tau / 2 as tau -> 0 and g(0) = 0 (the division
    is guarded by selection). Rounding: g's absolute error is that of alpha / tau, a few float64 eps,
    which moves the depth by about eps / s: nothing for the densities here, 1e-10 at s = 1e-6.
    """
    a = starts.clamp(near, far)
    b = torch.maximum(ends.clamp(near, far), a)
    lengths = b - a
    tau = density * lengths  # [B, K]
    alpha = -torch.expm1(-tau)
    tau_before = torch.cat([torch.zeros_like(tau[:, :1]), torch.cumsum(tau[:, :-1], -1)], -1)
    transmittance = torch.exp(-tau_before)  # entering each segment
    positive = tau > 0
    g = torch.where(positive, alpha / torch.where(positive, tau, 1), 1) - torch.exp(-tau)
    opacity = -torch.expm1(-tau.sum(-1))
    moment = (transmittance * (a * alpha + lengths * g)).sum(-1)
    absorbed = opacity > 0
    depth = torch.where(absorbed, moment / torch.where(absorbed, opacity, 1), far)
    return opacity, depth


def sphere_crossing(origins: Tensor, directions: Tensor, centre: Tensor,
                    radius: float) -> tuple[Tensor, Tensor, Tensor]:
    """Where rays [B, 3] (unit directions) cross a sphere: (t_in, t_out, hit), each [B].

    With b = d . (o - c) and p = (o - c) - b d the ray's closest approach to the centre, the crossings
    are t = -b -+ sqrt(r^2 - |p|^2); a ray with |p| >= r misses (hit false; a tangent ray crosses a set
    of zero length). |p|^2 is computed directly, not as |o - c|^2 - b^2, which cancels for rays aimed
    near the centre.
    """
    offset = origins - centre
    b = (directions * offset).sum(-1)
    closest = offset - b[:, None] * directions
    discriminant = radius**2 - closest.square().sum(-1)
    hit = discriminant > 0
    half_chord = torch.sqrt(discriminant.clamp_min(0))
    return -b - half_chord, -b + half_chord, hit


def erf_difference(x: Tensor, y: Tensor) -> Tensor:
    """erf(x) - erf(y) without cancellation where x and y are both far out on the same side:
    there it is erfc(y) - erfc(x) (both positive) or erfc(-x) - erfc(-y) (both negative)."""
    both_positive, both_negative = (x > 0) & (y > 0), (x < 0) & (y < 0)
    return torch.where(both_positive, torch.special.erfc(y) - torch.special.erfc(x),
                       torch.where(both_negative, torch.special.erfc(-x) - torch.special.erfc(-y),
                                   torch.special.erf(x) - torch.special.erf(y)))


class AnalyticField(nn.Module, abc.ABC):
    """A field of one colour ``colour`` whose density has a closed form, with the exact render of any ray.

    Subclasses give ``density`` (positions [..., 3] -> sigma [...]) and ``opacity_and_depth`` (float64
    rays -> float64 opacity and depth [B], see the module's conventions). No parameters: the renderer's
    coarse and fine networks may share one instance.
    """

    def __init__(self, colour: tuple[float, float, float]):
        super().__init__()
        self.colour = tuple(colour)

    @abc.abstractmethod
    def density(self, positions: Tensor) -> Tensor:
        """sigma [...] at positions [..., 3]."""

    @abc.abstractmethod
    def opacity_and_depth(self, origins: Tensor, directions: Tensor, near: float,
                          far: float) -> tuple[Tensor, Tensor]:
        """The exact opacity and depth [B] of float64 rays [B, 3] over [near, far]."""

    def forward(self, positions: Tensor, directions: Tensor) -> FieldOutputs:
        """positions [..., S, 3], directions [..., S or 1, 3] (unused) -> rgb [..., S, 3], sigma [..., S]."""
        return self.coloured(self.positional(positions), directions)

    def positional(self, positions: Tensor) -> PositionalOutputs:
        """The density at positions [..., 3], the positions themselves as the features (``NeRFField``'s stages)."""
        return PositionalOutputs(sigma=self.density(positions), features=positions)

    def coloured(self, positional: PositionalOutputs, directions: Tensor) -> FieldOutputs:
        """The field's outputs from its ``positional`` ones; ``directions`` unused."""
        rgb = positional.features.new_tensor(self.colour).expand(*positional.sigma.shape, 3)
        return FieldOutputs(rgb=rgb, sigma=positional.sigma)

    def truth(self, origins: Tensor, directions: Tensor, near: float, far: float,
              background: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> dict[str, Tensor]:
        """The exact render of rays ``origins``, ``directions`` [B, 3] (unit directions) over [near, far]:
        ``opacity`` [B], ``depth`` [B] and ``rgb`` [B, 3] = opacity c + (1 - opacity) background, float64."""
        origins, directions = origins.double(), directions.double()
        opacity, depth = self.opacity_and_depth(origins, directions, near, far)
        colour, background = origins.new_tensor(self.colour), origins.new_tensor(background)
        rgb = opacity[:, None] * colour + (1 - opacity[:, None]) * background
        return {"opacity": opacity, "depth": depth, "rgb": rgb}


class Slab(AnalyticField):
    """Density ``density`` between two parallel planes, lower < n . x < upper (n a unit ``normal``), else 0.

    A ray crosses it on one segment: n . (o + t d) runs from ``lower`` to ``upper`` for t between
    (lower - n . o) / (n . d) and (upper - n . o) / (n . d); a ray parallel to the planes (n . d = 0) is
    inside for every t or for none.
    """

    def __init__(self, normal=(0.0, 0.0, 1.0), lower: float = -0.5, upper: float = 0.5, density: float = 3.0,
                 colour=(0.9, 0.3, 0.1)):
        super().__init__(colour)
        norm = math.hypot(*normal)
        self.normal = tuple(n / norm for n in normal)
        self.lower, self.upper, self.sigma = lower, upper, density

    def density(self, positions: Tensor) -> Tensor:
        height = (positions * positions.new_tensor(self.normal)).sum(-1)
        inside = (height > self.lower) & (height < self.upper)
        return torch.where(inside, positions.new_tensor(self.sigma), 0)

    def opacity_and_depth(self, origins, directions, near, far):
        normal = origins.new_tensor(self.normal)
        height, rate = origins @ normal, directions @ normal  # [B]
        moving = rate != 0
        safe_rate = torch.where(moving, rate, 1)
        t_lower, t_upper = (self.lower - height) / safe_rate, (self.upper - height) / safe_rate
        inside = (height > self.lower) & (height < self.upper)
        parallel_start = torch.where(inside, -torch.inf, torch.inf)  # inside: all of the ray; outside: none
        starts = torch.where(moving, torch.minimum(t_lower, t_upper), parallel_start)
        ends = torch.where(moving, torch.maximum(t_lower, t_upper), torch.inf)
        return segments_truth(starts[:, None], ends[:, None], self.sigma, near, far)


class Shell(AnalyticField):
    """Density ``density`` in a spherical shell, ``radius`` < |x - centre| < radius + ``thickness``, else 0.

    A ray crosses it on up to two segments: [outer in, inner in] and [inner out, outer out] when it
    meets the inner sphere, else the one segment [outer in, outer out] (the second left empty).
    """

    def __init__(self, centre=(0.0, 0.0, 0.0), radius: float = 1.0, thickness: float = 0.1, density: float = 10.0,
                 colour=(0.1, 0.6, 0.3)):
        super().__init__(colour)
        self.centre, self.radius, self.thickness, self.sigma = tuple(centre), radius, thickness, density

    def density(self, positions: Tensor) -> Tensor:
        distance2 = (positions - positions.new_tensor(self.centre)).square().sum(-1)
        inside = (distance2 > self.radius**2) & (distance2 < (self.radius + self.thickness) ** 2)
        return torch.where(inside, positions.new_tensor(self.sigma), 0)

    def opacity_and_depth(self, origins, directions, near, far):
        centre = origins.new_tensor(self.centre)
        outer_in, outer_out, outer_hit = sphere_crossing(origins, directions, centre, self.radius + self.thickness)
        inner_in, inner_out, inner_hit = sphere_crossing(origins, directions, centre, self.radius)
        first_end = torch.where(inner_hit, inner_in, outer_out)
        second_start = torch.where(inner_hit, inner_out, outer_out)
        starts = torch.stack([outer_in, second_start], -1)
        ends = torch.stack([first_end, outer_out], -1)
        ends = torch.where(outer_hit[:, None], ends, starts)  # a miss: two empty segments
        return segments_truth(starts, ends, self.sigma, near, far)


class GaussianBlob(AnalyticField):
    """sigma(x) = peak exp(-|x - centre|^2 / (2 r^2)), r = ``radius``.

    Along a ray, |x(t) - c|^2 = |p|^2 + (t - t*)^2 with t* = d . (c - o) and p the closest approach, so
    the optical depth is closed form,

        tau(t) = A r sqrt(pi / 2) [erf((t - t*) / (sqrt(2) r)) - erf((near - t*) / (sqrt(2) r))],
        A = peak exp(-|p|^2 / (2 r^2)),

    and so is the opacity. The depth's int_near^far (1 - T) dt has no closed form: it is integrated in
    float64 by ``order``-point Gauss-Legendre on ``panels`` equal panels of [near, far]. The integrand
    is smooth on the scale r, so panels about r wide suffice: for r = 0.3 over [2, 6], 16 panels agree
    with 512 to 1e-15, and the defaults (256) are converged to rounding (``tests/nerf/test_analytic.py``).
    """

    def __init__(self, centre=(0.0, 0.0, 0.0), radius: float = 0.3, peak: float = 5.0, colour=(0.2, 0.3, 0.9),
                 panels: int = 256, order: int = 8):
        super().__init__(colour)
        self.centre, self.radius, self.peak = tuple(centre), radius, peak
        self.panels, self.order = panels, order

    def density(self, positions: Tensor) -> Tensor:
        distance2 = (positions - positions.new_tensor(self.centre)).square().sum(-1)
        return self.peak * torch.exp(-distance2 / (2 * self.radius**2))

    def optical_depth(self, origins: Tensor, directions: Tensor, near: float, t: Tensor) -> Tensor:
        """tau from ``near`` to each t [B, N] of rays [B, 3]: [B, N]."""
        offset = origins.new_tensor(self.centre) - origins
        closest_t = (directions * offset).sum(-1)  # t*
        closest2 = (offset - closest_t[:, None] * directions).square().sum(-1)  # |p|^2
        scale = math.sqrt(2) * self.radius
        amplitude = self.peak * torch.exp(-closest2 / (2 * self.radius**2)) * self.radius * math.sqrt(math.pi / 2)
        start = (near - closest_t[:, None]) / scale
        return amplitude[:, None] * erf_difference((t - closest_t[:, None]) / scale, start)

    def opacity_and_depth(self, origins, directions, near, far):
        B, _ = origins.shape  # rays, xyz
        nodes, weights = (origins.new_tensor(v) for v in np.polynomial.legendre.leggauss(self.order))  # on [-1, 1]
        width = (far - near) / self.panels
        centres = near + width * (torch.arange(self.panels, dtype=origins.dtype) + 0.5)
        t = (centres[:, None] + width / 2 * nodes).reshape(1, -1)  # [1, panels * order]
        absorbed_before = -torch.expm1(-self.optical_depth(origins, directions, near, t.expand(B, -1)))  # 1 - T(t)
        integral = (absorbed_before * (width / 2 * weights).repeat(self.panels)).sum(-1)
        far_t = torch.full((B, 1), far, dtype=origins.dtype)
        opacity = -torch.expm1(-self.optical_depth(origins, directions, near, far_t)[:, 0])
        absorbed = opacity > 0
        depth = torch.where(absorbed, far - integral / torch.where(absorbed, opacity, 1), far)
        return opacity, depth


# Measuring a renderer against the truth: rays, errors, the cost of an accuracy.


def aimed_rays(n: int, generator: torch.Generator, impact: float, distance: tuple[float, float],
               cone_degrees: float = 180.0) -> tuple[Tensor, Tensor]:
    """``n`` random float64 rays (origins, unit directions [n, 3]) that pass near the world origin.

    Directions are uniform on the cap within ``cone_degrees`` of -z; each ray passes the origin at a
    distance drawn uniformly over the disc of radius ``impact`` perpendicular to it, at a distance along
    the ray drawn uniformly from ``distance``. So what a field centred at the origin puts on a ray lands
    anywhere relative to a sample grid along it.
    """
    def uniform(low: float, high: float) -> Tensor:
        return low + (high - low) * torch.rand(n, generator=generator, dtype=torch.float64)

    cos_theta = uniform(math.cos(math.radians(cone_degrees)), 1.0)
    sin_theta, phi = torch.sqrt(1 - cos_theta**2), uniform(0, 2 * math.pi)
    directions = torch.stack([sin_theta * torch.cos(phi), sin_theta * torch.sin(phi), -cos_theta], -1)
    across = torch.stack([torch.cos(phi) * cos_theta, torch.sin(phi) * cos_theta, sin_theta], -1)
    sideways = torch.linalg.cross(directions, across)  # across and sideways: unit, perpendicular to d
    radius, angle = impact * torch.sqrt(uniform(0, 1)), uniform(0, 2 * math.pi)
    closest = radius[:, None] * (torch.cos(angle)[:, None] * across + torch.sin(angle)[:, None] * sideways)
    return closest - uniform(*distance)[:, None] * directions, directions


def render_errors(rendered: dict[str, Tensor], truth: dict[str, Tensor]) -> dict[str, float]:
    """Mean absolute errors of rendered rays against their truth (both dicts of ``opacity`` [B],
    ``depth`` [B], ``rgb`` [B, 3]): ``opacity``, ``rgb`` (over rays and channels), and ``depth`` weighted
    by the true opacity, sum_b opacity_b |depth error_b| / sum_b opacity_b: the depth of a ray matters
    in proportion to the light it stops, and a ray that barely absorbs has an ill-conditioned depth."""
    weight = truth["opacity"]
    depth_error = (rendered["depth"].double() - truth["depth"]).abs()
    total = weight.sum()
    return {"opacity": (rendered["opacity"].double() - truth["opacity"]).abs().mean().item(),
            "depth": ((weight * depth_error).sum() / torch.where(total > 0, total, 1)).item(),
            "rgb": (rendered["rgb"].double() - truth["rgb"]).abs().mean().item()}


def cost_for_error(target: float, costs: list[float], errors: list[float]) -> float | None:
    """The cost (evaluations per ray, seconds) at which a measured error curve gets below ``target`` for
    good: from the first measured point after which every error is <= target, interpolated in log-log
    with the point before it. ``costs[0]`` if every point is below, None if the last one is not.
    costs ascending, errors >= 0, one per cost."""
    k = len(errors)
    while k > 0 and errors[k - 1] <= target:
        k -= 1
    if k == len(errors):
        return None
    if k == 0:
        return costs[0]
    before, after = errors[k - 1], errors[k]  # before > target >= after
    fraction = math.log(before / target) / math.log(before / after) if after > 0 else 0.0
    return costs[k - 1] * (costs[k] / costs[k - 1]) ** fraction


def slab(sigma: float = 3.0, half_width: float = 0.5, shift: float = 0.0) -> Slab:
    """Density ``sigma`` where |z - shift| < half_width, else 0; colour (0.2, 0.4, 0.6)."""
    return Slab(lower=shift - half_width, upper=shift + half_width, density=sigma, colour=(0.2, 0.4, 0.6))


def rays_down_z(n: int) -> tuple[Tensor, Tensor]:
    """``n`` rays from (0, 0, 4) straight down z (float64): origins and directions [n, 3]."""
    origins = torch.zeros(n, 3, dtype=torch.float64)
    origins[:, 2] = 4.0
    directions = torch.zeros(n, 3, dtype=torch.float64)
    directions[:, 2] = -1.0
    return origins, directions
