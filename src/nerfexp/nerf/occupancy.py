"""An occupancy grid: which cells of the scene's bounding box hold density, so that the renderer can
leave out samples in empty space (``acceleration=occupancy``; nerfacc's ``OccGridEstimator`` idea,
written in torch so that it runs on the CPU and on GPUs alike).

Conventions: ``aabb`` [2, 3] is the box (lower corner, upper corner); the grid has ``resolution``^3
cells, cell (i, j, k) covering ``lower + [i, i+1] x [j, j+1] x [k, k+1] * cell_size``, flattened as
``(i * R + j) * R + k``. A cell's ``density`` [R^3] is a running estimate of the largest density in it;
a cell is *occupied* when that estimate exceeds the density threshold (see ``OccupancyGrid``).
Everything outside the box counts as empty: no sample there is evaluated.
"""

import logging
import math
from collections.abc import Callable, Mapping, Sequence
from typing import ClassVar

import torch
from torch import Tensor

from nerfexp.domains import BOOLEAN, COUNT, FRACTION, NONNEGATIVE_COUNT, Applies, Memory, Rule, optional, real
from nerfexp.nerf.bounds import Bounded
from nerfexp.sizes import grid_bytes

log = logging.getLogger(__name__)


def cell_indices(points: Tensor, aabb: Tensor, resolution: int) -> tuple[Tensor, Tensor]:
    """The flat index [...] of the cell holding each point [..., 3], and whether it lies inside the box [...].

    Points outside the box (or NaN) get index 0 and ``inside`` false; the box is half-open, [lower, upper).
    """
    unit = (points - aabb[0]) / (aabb[1] - aabb[0])  # [..., 3], in [0, 1) inside the box
    inside = ((unit >= 0) & (unit < 1)).all(-1)
    ijk = (unit * resolution).floor().clamp(0, resolution - 1).long()
    ijk = torch.where(inside[..., None], ijk, 0)
    return (ijk[..., 0] * resolution + ijk[..., 1]) * resolution + ijk[..., 2], inside


def cell_corners(resolution: int, device: torch.device | None = None) -> Tensor:
    """The integer lower corner (i, j, k) of every cell, in flat-index order: [R^3, 3] float32."""
    axis = torch.arange(resolution, dtype=torch.float32, device=device)
    return torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)


def density_threshold(opacity: float, cell_diagonal: float) -> float:
    """The density sigma at which light crossing a cell along its diagonal (the longest path through it)
    is absorbed with probability ``opacity``: 1 - exp(-sigma diagonal) = opacity, so
    sigma = -log(1 - opacity) / diagonal."""
    return -math.log1p(-opacity) / cell_diagonal


class OccupancyGrid(Bounded):
    """A binary grid of occupied cells over the box ``aabb``, kept up to date from the density field.

    Every ``update_every`` training steps (``update``), the density of the networks is evaluated at one uniformly
    jittered point in each of a set of cells: all cells during the first ``warmup_steps`` steps, afterwards a random
    share ``update_fraction`` of them (nerfacc's quarter: each cell on average every fourth update) and, with
    ``update_occupied``, as many again drawn from the occupied cells (nerfacc's and Instant-NGP's rule: a cell that
    holds density is looked at about twice as often, so it forgets a density that went away sooner). During the
    warm-up a cell's estimate is its latest evaluation; afterwards it becomes max(decay * old, new): it remembers a
    density it has seen (a jittered point can miss a thin surface once) and forgets it at rate ``decay`` per
    evaluation when the density goes away. The warm-up keeps no memory because what it would remember is the
    untrained field: its density everywhere (softplus(-1) = 0.31 with the default field) lies above the threshold of
    a cell a few hundredths of the box wide, and forgetting it at ``decay`` per evaluation, one evaluation every
    ``update_every / update_fraction`` steps, takes longer than a short run. A cell is occupied when its estimate
    exceeds min(sigma_t, mean of all estimates), where sigma_t is the density at which light crossing the cell along
    its diagonal loses the fraction ``threshold`` (``density_threshold``); the mean guards the first updates, when
    the whole field is faint. Until the first update every cell is occupied. With ``march_steps`` = n, the length
    light crosses is not the cell's diagonal but a step of 1/n of the box's diagonal (Instant-NGP and nerfacc: 1024
    steps; their grids hold the optical thickness over one marching step): a cell is occupied only where one
    sample's interval of that length would absorb ``threshold``, so sigma_t is resolution / n times the diagonal's.

    ``alpha_threshold`` (nerfacc's ``alpha_thre``) is read by the renderer: a sample in an occupied cell whose
    alpha = 1 - exp(-sigma delta) over its own interval is below it gets no colour evaluation and absorbs
    nothing, as a sample in an empty cell; 0 keeps every sample the grid keeps.

    With ``early_stop_transmittance`` > 0 rays stop there: the renderer marches them in ``segments`` runs of
    samples and evaluates a run only for rays that let through at least that much light in front of
    it (see ``VolumeRenderer``). 0, the default, turns it off (why, measured: docs/acceleration.md, early
    termination).

    The bounds are a buffer: ``aabb`` [2, 3] here or, left None, set once from the scene
    (``set_bounds``, which ``NeRFModule`` calls when training starts). ``density``, ``occupied`` and
    ``aabb`` are saved in checkpoints, so a resumed run continues with the same grid.

    It is not a sampler but a component beside them: the renderer queries the networks through it, whichever
    sampler placed the samples (``VolumeRenderer``).
    """

    DOMAINS: ClassVar[dict[str, Rule]] = {
        "resolution": COUNT,
        "threshold": real(0, 1, above=True),
        "decay": FRACTION,
        "warmup_steps": NONNEGATIVE_COUNT,
        "update_every": COUNT,
        "early_stop_transmittance": real(0, 1),
        "segments": COUNT,
        "alpha_threshold": real(0, 1),
        "march_steps": optional(COUNT, "the cell's diagonal"),
        "update_occupied": BOOLEAN,
        "update_fraction": real(0, 1, above=True),
    }
    APPLIES: ClassVar[dict[str, Applies]] = {  # nerfexp.domains: when an argument does nothing
        "segments": lambda grid: (None if grid.get("early_stop_transmittance")
                                  else "acceleration.grid.early_stop_transmittance=0 (no early termination: "
                                       "set it > 0, e.g. 1e-4, to march in segments)"),
    }
    SCENE_FIELDS: ClassVar[tuple[str, ...]] = ("aabb",)  # its cells divide the scene's box

    @staticmethod
    def MEMORY(config: Mapping) -> list[Memory]:
        """Its cells' densities."""
        return [(("resolution",), f"an occupancy grid of {config['resolution']}^3 cells",
                 grid_bytes(config["resolution"]))]

    def __init__(self, resolution: int = 32, threshold: float = 0.01, decay: float = 0.95, warmup_steps: int = 256,
                 update_every: int = 16, early_stop_transmittance: float = 0.0, segments: int = 4,
                 aabb: Sequence[Sequence[float]] | None = None, alpha_threshold: float = 0.0,
                 march_steps: int | None = None, update_occupied: bool = False, update_fraction: float = 0.25):
        super().__init__(aabb)
        checks = {"resolution": resolution >= 1, "threshold": 0 < threshold < 1, "decay": 0 <= decay <= 1,
                  "warmup_steps": warmup_steps >= 0, "update_every": update_every >= 1,
                  "early_stop_transmittance": 0 <= early_stop_transmittance < 1, "segments": segments >= 1,
                  "alpha_threshold": 0 <= alpha_threshold < 1, "march_steps": march_steps is None or march_steps >= 1,
                  "update_fraction": 0 < update_fraction <= 1}
        bad = [key for key, ok in checks.items() if not ok]
        if bad:
            values = {"resolution": resolution, "threshold": threshold, "decay": decay, "warmup_steps": warmup_steps,
                      "update_every": update_every, "early_stop_transmittance": early_stop_transmittance,
                      "segments": segments, "alpha_threshold": alpha_threshold, "march_steps": march_steps,
                      "update_fraction": update_fraction}
            raise ValueError(f"acceleration.grid.{bad[0]}: expected resolution >= 1, 0 < threshold < 1, "
                             f"0 <= decay <= 1, warmup_steps >= 0, update_every >= 1, 0 <= early_stop_transmittance "
                             f"< 1, segments >= 1, 0 <= alpha_threshold < 1, march_steps >= 1 or null, "
                             f"0 < update_fraction <= 1; "
                             f"got {bad[0]}={values[bad[0]]}")
        self.resolution = resolution
        self.threshold = threshold
        self.decay = decay
        self.warmup_steps = warmup_steps
        self.update_every = update_every
        self.early_stop_transmittance = early_stop_transmittance
        self.segments = segments
        self.alpha_threshold = alpha_threshold
        self.march_steps = march_steps
        self.update_occupied = update_occupied
        self.update_fraction = update_fraction
        # contracted positions -> world units per unit there (``SceneContraction.stretch``), set by the renderer
        # of a contracted scene: the cells' thresholds then follow the world lengths they span; None: the box's
        self.world_scale: Callable[[Tensor], Tensor] | None = None
        n_cells = resolution**3
        self.register_buffer("density", torch.zeros(n_cells))
        self.register_buffer("occupied", torch.ones(n_cells, dtype=torch.bool))

    @property
    def cell_size(self) -> Tensor:
        """[3]: the edge lengths of one cell."""
        return (self.aabb[1] - self.aabb[0]) / self.resolution

    def occupied_at(self, points: Tensor) -> Tensor:
        """Whether each point [..., 3] lies in an occupied cell inside the box: bool [...]."""
        self.require_bounds()
        index, inside = cell_indices(points, self.aabb.to(points.dtype), self.resolution)
        return inside & self.occupied[index]

    def due(self, step: int) -> bool:
        """Whether ``update`` re-evaluates cells at training step ``step``."""
        return step % self.update_every == 0

    @torch.no_grad()
    def update(self, step: int, density_fns: Sequence[Callable[[Tensor], Tensor]]) -> None:
        """Re-evaluate cells with ``density_fns`` (positions [N, 3] -> sigma [N]; the largest answer
        counts, so a cell is empty only where every network finds it empty) if ``due(step)``.

        Draws its jitter and its choice of cells from torch's global random numbers."""
        if not self.due(step):
            return
        cells = self.cells_to_update(step)
        corners = cell_corners(self.resolution, self.density.device)[cells]
        jitter = torch.rand(corners.shape, device=corners.device)
        points = self.aabb[0] + (corners + jitter) * self.cell_size  # [N, 3]
        sigma = torch.stack([fn(points).float() for fn in density_fns]).amax(0)
        if step < self.warmup_steps:  # every cell was just evaluated: no memory of the untrained field
            self.density[cells] = sigma
        else:
            self.density[cells] = torch.maximum(self.density[cells] * self.decay, sigma)
        self.mark_occupied()

    def mark_occupied(self) -> None:
        """``occupied`` from the estimates ``density``: above min(sigma_t, their mean) (see the class docstring)."""
        self.occupied.copy_(self.density > torch.clamp(self.density.mean(), max=self.cell_thresholds()))

    def cells_to_update(self, step: int) -> Tensor:
        """The flat indices [N] of the cells an update at ``step`` re-evaluates: all of them during the warm-up,
        afterwards a random share ``update_fraction`` of them and, with ``update_occupied``, as many drawn (with
        repetition) from the occupied ones, without duplicates: a cell drawn twice is evaluated once. Draws from
        torch's global random numbers."""
        n_cells = self.density.numel()
        device = self.density.device
        if step < self.warmup_steps:
            return torch.arange(n_cells, device=device)
        share = max(int(n_cells * self.update_fraction), 1)
        cells = torch.randperm(n_cells, device=device)[:share]
        occupied = self.occupied.nonzero().squeeze(-1)
        if not self.update_occupied or len(occupied) == 0:
            return cells
        drawn = occupied[torch.randint(len(occupied), (share,), device=device)]
        return torch.unique(torch.cat([cells, drawn]))

    def cell_thresholds(self) -> Tensor | float:
        """The density above which a cell is occupied (``density_threshold`` of the ``threshold_length``): one
        number for the box's cells, or, with a ``world_scale``, one per cell [R^3] of that length in world units,
        taken at its corner farthest from the origin (the most stretched: a contracted scene's outer cells span
        long stretches of the world, so they are occupied at densities far below the inner cells'; those on the
        contraction's shell, of infinite extent, at any density)."""
        length = self.threshold_length
        if self.world_scale is None:
            return density_threshold(self.threshold, length)
        lower = self.aabb[0] + cell_corners(self.resolution, self.aabb.device) * self.cell_size  # [R^3, 3]
        farthest = torch.where(lower.abs() > (lower + self.cell_size).abs(), lower, lower + self.cell_size)
        world_length = length * self.world_scale(farthest)
        return -math.log1p(-self.threshold) / world_length  # density_threshold per cell; 0 where infinite

    @property
    def threshold_length(self) -> float:
        """The length (box units) over which light crossing an occupied cell loses at least ``threshold``: the
        cell's diagonal, or with ``march_steps`` = n one step of n along the box's diagonal."""
        diagonal = torch.linalg.vector_norm(self.cell_size)
        if self.march_steps is None:
            return float(diagonal)
        return float(diagonal) * self.resolution / self.march_steps
