"""Ray marching through the occupancy grid (``sampler=march``; Instant-NGP's and nerfacc's ``OccGridEstimator``
sampling): a ray's samples are the steps of a fixed length along it whose midpoints lie in occupied cells of the
grid, so they are dense where the scene is and absent where it is not, as many per ray as the scene needs.

Conventions: a march's steps are intervals [t_starts, t_ends] along rays o + t d, in units of t, each standing
for its midpoint; packed (``Marched``), the occupied steps of every ray one after another ([N] each, ray after
ray, in order along each ray) with each ray's ``counts`` [B]; per ray (``nerfexp.nerf.samplers.Spans``), [B, K]
tensors holding each ray's steps first and empty steps (``valid`` false, zero length at far) after them. The grid
is the renderer's (``acceleration=occupancy``): its box, cells and occupied flags; with a contraction the
positions looked up are contracted (``nerfexp.nerf.contraction``) and the march runs over the rays' whole
[near, far].

The march of a ray: from where it enters the box (or near, if later) to where it leaves (or far), steps of
``step`` long in the grid's space (``GridMarchSampler``: the box's diagonal / n_steps), jittered in training by
one offset in [0, 1) steps per ray; with a cone angle c each step is max(step, c t |d|) long, so steps grow with
distance (Instant-NGP's cone tracing; by default on with a contraction). At most ``max_samples`` occupied steps
per ray are kept (the first ones): what bounds a batch's memory. The fused CPU kernel
(``nerfexp.kernels``, grid_march.cpp) crosses an empty cell in one jump; the torch path (GPUs, and the
reference the tests hold it to) looks up every step; both keep the same steps, bit for bit, without a contraction.
"""

from collections.abc import Mapping
from typing import ClassVar, NamedTuple

import torch
from torch import Tensor

from nerfexp.domains import COUNT, Rule, optional, real
from nerfexp.kernels import kernel
from nerfexp.nerf.contraction import SceneContraction
from nerfexp.nerf.occupancy import OccupancyGrid, cell_indices
from nerfexp.nerf.samplers import Rays, Sampler, Spans, Steps

NORM_CODES = {"l2": 1, "linf": 2}  # the kernel's codes of a contraction's norm (0: no contraction)
CONE_WITH_CONTRACTION = 1 / 256  # Instant-NGP's cone angle for large scenes: each step 1/256 of its distance
TORCH_CHUNK = 1 << 21  # steps the torch path looks up at once (rays x steps)


class Marched(NamedTuple):
    """The occupied steps of a batch of B rays, packed: ``t_starts``, ``t_ends`` [N], ray after ray; ``counts`` [B]
    (int64), each ray's number of them."""

    t_starts: Tensor
    t_ends: Tensor
    counts: Tensor


class March(NamedTuple):
    """What a march looks up and how it steps: the grid's ``occupied`` flags [R^3] (bool) of ``resolution`` cells
    per side over its box ``aabb`` [2, 3]; ``step`` (distance units of the positions looked up), ``cone_angle``
    (0: fixed steps) and ``max_samples`` per ray; ``contraction``: the positions' (None: none)."""

    occupied: Tensor
    resolution: int
    aabb: Tensor
    step: float
    cone_angle: float
    max_samples: int
    contraction: SceneContraction | None

    @property
    def fixed(self) -> bool:
        """Whether every step is ``step`` long through the box (no cone angle, no contraction)."""
        return self.cone_angle == 0 and self.contraction is None


def base_steps(directions: Tensor, step: float) -> Tensor:
    """The march's step in units of t for rays of ``directions`` [B, 3]: step / |d| [B] (worked out here for both
    paths, so that they step alike)."""
    return step / torch.linalg.vector_norm(directions, dim=-1)


def box_span(origins: Tensor, directions: Tensor, near: Tensor, far: Tensor, aabb: Tensor) -> tuple[Tensor, Tensor]:
    """Where rays o + t d (``origins``, ``directions`` [B, 3]) are inside the box ``aabb`` [2, 3] within [near, far]
    [B]: (lo, hi) [B], lo >= hi where a ray misses it (the slab method; along an axis the ray runs parallel to, it
    is inside only where its origin lies in [lower, upper))."""
    lo, hi = near.clone(), far.clone()
    for a in range(3):
        o, d = origins[:, a], directions[:, a]
        parallel = d == 0
        safe = torch.where(parallel, 1, d)
        t_a, t_b = (aabb[0, a] - o) / safe, (aabb[1, a] - o) / safe
        lo = torch.where(parallel, lo, torch.maximum(lo, torch.minimum(t_a, t_b)))
        hi = torch.where(parallel, hi, torch.minimum(hi, torch.maximum(t_a, t_b)))
        hi = torch.where(parallel & ((o < aabb[0, a]) | (o >= aabb[1, a])), -torch.inf, hi)
    return lo, hi


def occupied_steps(march: March, origins: Tensor, directions: Tensor, starts: Tensor, ends: Tensor) -> Tensor:
    """Whether the steps [starts, ends] ([B, K] each) of rays o + t d have their midpoints in occupied cells inside
    the box (``OccupancyGrid.occupied_at``'s arithmetic; contracted first where the march has a contraction):
    bool [B, K]."""
    mid = 0.5 * (starts + ends)
    points = origins[:, None, :] + directions[:, None, :] * mid[..., None]  # [B, K, 3]
    if march.contraction is not None:
        points = march.contraction(points)
    index, inside = cell_indices(points, march.aabb.to(points.dtype), march.resolution)
    return inside & march.occupied[index]


def first_kept(hit: Tensor, max_samples: int) -> Tensor:
    """The first ``max_samples`` true entries of each row of ``hit`` [B, K]: bool [B, K]."""
    return hit & (hit.cumsum(-1) <= max_samples)


def march_fixed(march: March, origins: Tensor, directions: Tensor, near: Tensor, far: Tensor,
                offsets: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The torch path's fixed steps through the box, every step looked up, in chunks of rays of at most about
    ``TORCH_CHUNK`` steps: (t_starts, t_ends [N], counts [B])."""
    lo, hi = box_span(origins, directions, near, far, march.aabb.to(origins.dtype))
    base = base_steps(directions, march.step)
    n_steps = torch.where(hi > lo, torch.ceil((hi - lo) / base - offsets), 0).clamp_min(0)  # steps starting < hi
    longest = int(n_steps.max().item()) if len(origins) else 0
    count = max(1, TORCH_CHUNK // (longest + 1))  # rays per chunk
    parts = []
    start = 0
    while start < len(origins):
        chunk = slice(start, start + count)
        k = torch.arange(longest + 1, dtype=origins.dtype, device=origins.device)  # [K]
        low, high, b, u = lo[chunk, None], hi[chunk, None], base[chunk, None], offsets[chunk, None]
        a = low + (k + u) * b  # [C, K], in the kernel's order of operations
        e = torch.minimum(low + (k + 1 + u) * b, high)
        hit = (a < high) & occupied_steps(march, origins[chunk], directions[chunk], a, e)
        kept = first_kept(hit, march.max_samples)
        parts.append((a[kept], e[kept], kept.sum(-1)))
        start += count
    return tuple(torch.cat(column) for column in zip(*parts)) if parts else (
        origins.new_zeros(0), origins.new_zeros(0), torch.zeros(0, dtype=torch.long, device=origins.device))


def march_growing(march: March, origins: Tensor, directions: Tensor, near: Tensor, far: Tensor,
                  offsets: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The torch path's growing steps (a cone angle, or a contraction), one step of every ray at a time until each
    ray has reached its end or ``max_samples``: (t_starts, t_ends [N], counts [B])."""
    if march.contraction is None:
        lo, hi = box_span(origins, directions, near, far, march.aabb.to(origins.dtype))
    else:
        lo, hi = near, far
    base = base_steps(directions, march.step)
    a = lo + offsets * torch.maximum(base, march.cone_angle * lo)
    counts = torch.zeros(len(origins), dtype=torch.long, device=origins.device)
    starts, ends, hits = [], [], []
    while True:
        going = (a < hi) & (counts < march.max_samples)
        if not going.any():
            break
        b = torch.minimum(a + torch.maximum(base, march.cone_angle * a), hi)
        hit = going & occupied_steps(march, origins, directions, a[:, None], b[:, None])[:, 0]
        starts.append(a)
        ends.append(b)
        hits.append(hit)
        counts += hit
        a = torch.where(going & (b > a), b, torch.inf)  # a step too small to move t ends the march, as the kernel's
    if not hits:
        return origins.new_zeros(0), origins.new_zeros(0), counts
    hit = torch.stack(hits, -1)  # [B, K]
    return torch.stack(starts, -1)[hit], torch.stack(ends, -1)[hit], counts


def march_rays(march: March, origins: Tensor, directions: Tensor, near: Tensor, far: Tensor,
               offsets: Tensor) -> Marched:
    """The occupied steps of rays o + t d (``origins``, ``directions`` [B, 3]) between ``near`` and ``far`` [B], each
    ray's steps shifted by ``offsets`` [B] in [0, 1) steps: by the fused kernel where the rays are float32 on the
    CPU and it is built, else by the torch path."""
    fused = kernel("grid_march") if origins.device.type == "cpu" and origins.dtype == torch.float32 else None
    if fused is None:
        march_torch = march_fixed if march.fixed else march_growing
        return Marched(*march_torch(march, origins, directions, near, far, offsets))
    contraction = march.contraction
    centre = (torch.zeros(3) if contraction is None else contraction.centre).float().contiguous()
    radius = 1.0 if contraction is None else float(contraction.radius)
    norm = 0 if contraction is None else NORM_CODES[contraction.norm]
    base = base_steps(directions, march.step).contiguous()
    starts, ends, counts = fused.march(origins.contiguous(), directions.contiguous(), near.contiguous(),
                                       far.contiguous(), offsets.contiguous(), base, march.occupied.contiguous(),
                                       march.resolution, march.aabb.float().contiguous(), march.cone_angle,
                                       march.max_samples, centre, radius, norm)
    return Marched(starts, ends, counts)


def spans_of(marched: Marched, far: Tensor) -> Spans:
    """The packed steps of ``marched`` as each ray's row (``Spans``, [B, K], K the most steps of a ray, at least 1):
    its steps first, then empty ones of zero length at the ray's ``far`` [B] (``valid`` false)."""
    B = len(marched.counts)  # rays
    K = max(int(marched.counts.max().item()) if B else 0, 1)
    first = marched.counts.cumsum(0) - marched.counts  # [B] each ray's first place in the packed arrays
    ray = torch.repeat_interleave(torch.arange(B, device=far.device), marched.counts)  # [N]
    place = torch.arange(len(ray), device=far.device) - first[ray]  # [N] each step's place in its ray
    starts = far[:, None].expand(B, K).clone()
    ends = starts.clone()
    starts[ray, place] = marched.t_starts.to(far.dtype)
    ends[ray, place] = marched.t_ends.to(far.dtype)
    valid = torch.zeros(B, K, dtype=torch.bool, device=far.device)
    valid[ray, place] = True
    return Spans(t_starts=starts, t_ends=ends, valid=valid)


class GridMarchSampler(Sampler):
    """Samples where the occupancy grid says the scene is: each ray marched in steps of the box's diagonal /
    ``n_steps`` (growing by ``cone_angle`` times their distance; None: ``CONE_WITH_CONTRACTION`` where the renderer
    has a contraction, else 0), each step in an occupied cell a sample standing for its interval, at most
    ``max_samples`` per ray; one network (named "coarse", as every one-network sampler's) renders them
    (``Steps.composited`` with the steps' ``Spans``). Needs the renderer's occupancy grid
    (``acceleration=occupancy``). With the grid's early termination (``acceleration.grid.early_stop_transmittance``)
    a ray's steps are evaluated in runs, the later ones only while light is left (``VolumeRenderer``)."""

    DOMAINS: ClassVar[dict[str, Rule]] = {
        "n_steps": COUNT,
        # a step longer than 1/8 of the distance travelled skips surfaces a cell holds (Instant-NGP caps its cone
        # at 1/128); 0 keeps every step the base length
        "cone_angle": optional(real(0, 1 / 8), "1/256 with a contraction, else 0"),
        "max_samples": COUNT,
    }
    NEEDS_GRID: ClassVar[bool] = True  # the renderer refuses it without acceleration=occupancy

    def __init__(self, n_steps: int = 1024, cone_angle: float | None = None, max_samples: int = 256):
        super().__init__()
        if n_steps < 1 or max_samples < 1 or not (cone_angle is None or 0 <= cone_angle <= 1 / 8):
            raise ValueError(f"model.renderer.sampler: expected n_steps >= 1, 0 <= cone_angle <= 1/8 or null, "
                             f"max_samples >= 1; got n_steps={n_steps}, cone_angle={cone_angle}, "
                             f"max_samples={max_samples}")
        self.n_steps = n_steps
        self.cone_angle = cone_angle
        self.max_samples = max_samples

    @staticmethod
    def SAMPLES_PER_RAY(config: Mapping) -> tuple[int, tuple[str, ...]]:
        """At most ``max_samples`` per ray: a batch's network evaluations are bounded by it."""
        return config["max_samples"], ("max_samples",)

    @property
    def samples_per_ray(self) -> int:
        return self.max_samples

    def kernels(self) -> tuple[str, ...]:
        return ("grid_march",)

    def march(self, grid: OccupancyGrid, contraction: SceneContraction | None) -> March:
        """This sampler's march through ``grid`` (its box in the space the grid's positions live in: contracted
        where there is a ``contraction``, whose inner region's radius gives one contracted unit in world units)."""
        grid.require_bounds()
        diagonal = float(torch.linalg.vector_norm(grid.aabb[1] - grid.aabb[0]))
        scale = 1.0 if contraction is None else float(contraction.radius)
        cone = self.cone_angle if self.cone_angle is not None else (
            0.0 if contraction is None else CONE_WITH_CONTRACTION)
        return March(occupied=grid.occupied, resolution=grid.resolution, aabb=grid.aabb,
                     step=diagonal * scale / self.n_steps, cone_angle=cone, max_samples=self.max_samples,
                     contraction=contraction)

    def render(self, rays: Rays, steps: Steps, deterministic: bool) -> dict[str, dict[str, Tensor]]:
        if steps.grid is None:
            raise ValueError("sampler=march marches through the occupancy grid: it needs acceleration=occupancy")
        B = len(rays.origins)  # rays
        offsets = (torch.zeros(B, dtype=rays.origins.dtype, device=rays.origins.device) if deterministic
                   else torch.rand(B, dtype=rays.origins.dtype, device=rays.origins.device))
        marched = march_rays(self.march(steps.grid, steps.contraction), rays.origins, rays.directions, rays.near,
                             rays.far, offsets)
        spans = spans_of(marched, rays.far)
        t = 0.5 * (spans.t_starts + spans.t_ends)  # each step stands for its midpoint
        return {"coarse": steps.composited("coarse", rays, t, spans)}

