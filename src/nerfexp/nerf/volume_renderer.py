"""Rays to pixels: sample (a ``nerfexp.nerf.samplers.Sampler``, which asks the renderer's ``Steps``), query the
field(s), composite."""

from collections.abc import Callable
from typing import ClassVar

import torch
from torch import Tensor, nn

from nerfexp.domains import FAR, LOSS_WEIGHT, NEAR, Consistent, Rule, choice, optional
from nerfexp.nerf.appearance import AppearanceEmbedding
from nerfexp.nerf.backgrounds import BACKGROUNDS
from nerfexp.nerf.contraction import SceneContraction
from nerfexp.nerf.fields import FieldOutputs, PositionalOutputs
from nerfexp.nerf.occupancy import OccupancyGrid
from nerfexp.nerf.quadrature import composite, optical_depths, render_weights
from nerfexp.nerf.samplers import Rays, Sampler, Spans, needs_grid
from nerfexp.nerf.sampling import intervals


def final_output(outputs: dict[str, dict[str, Tensor]]) -> dict[str, Tensor]:
    """The output that is scored and shown: the fine network's, or the only network's without hierarchy."""
    return outputs["fine"] if "fine" in outputs else outputs["coarse"]


LOG2_SIZES_PER_OCTAVE = 3  # the packed batch sizes the networks see: at most 2^3 per doubling (``padded_size``)


def padded_size(n: int) -> int:
    """The packed batch size that evaluates n points: n rounded up to a multiple of 2^(floor(log2 n) - 3),
    so at most 8 sizes per doubling, each less than n / 8 above n.

    Why: on a CPU, a matrix product of a shape not met before costs oneDNN a new primitive (under bf16
    autocast a JIT-compiled kernel, more than the product itself: docs/acceleration.md), and a packed batch
    changes size every step; a few sizes, met again and again, come from its cache.

    >>> [padded_size(n) for n in (1, 7, 8, 9, 17, 1000, 1025)]
    [1, 7, 8, 9, 18, 1024, 1152]
    """
    quantum = 1 << max(n.bit_length() - 1 - LOG2_SIZES_PER_OCTAVE, 0)  # n.bit_length() - 1 = floor(log2 n)
    return -(-n // quantum) * quantum


def each_output(outputs: FieldOutputs, function: Callable[[Tensor], Tensor]) -> FieldOutputs:
    """``function`` of each output a field answered (None stays None)."""
    return FieldOutputs(*(None if out is None else function(out) for out in outputs))


def ask(field: Callable[..., FieldOutputs], points: Tensor | PositionalOutputs, directions: Tensor | None,
        codes: Tensor | None) -> FieldOutputs:
    """``field`` at ``points`` [N, 3] (or, for a field's ``coloured`` stage, its ``PositionalOutputs`` there) with
    ``directions`` [N, 3] and, where there are any, appearance ``codes`` [N, D] (``nerfexp.nerf.appearance``); a
    field is asked with codes only where the rays have them."""
    return field(points, directions) if codes is None else field(points, directions, codes)


def padded_rows(index: tuple[Tensor, ...]) -> tuple[Tensor, ...]:
    """The index tensors [N] of a packed batch made ``padded_size(N)`` long: the first rows again fill the rest
    (``padded_size``: few batch sizes for oneDNN's cache). [P] each."""
    n = len(index[0])
    return tuple(torch.cat([i, i[: padded_size(n) - n]]) for i in index)


def query_packed(field: Callable[..., FieldOutputs], points: Tensor,
                 viewdirs: Tensor | None, keep: Tensor, codes: Tensor | None = None) -> FieldOutputs:
    """Evaluate ``field`` only at the samples ``keep`` [B, S] (bool) of ``points`` [B, S, 3], rays' unit
    ``viewdirs`` [B, 3] (None for a density query, ``density_query``) and appearance ``codes`` [B, D] (or None),
    as one flat batch of N = keep.sum() points; the others get zeros (sigma = 0, rgb = 0).

    The batch is ``padded_size(N)`` long: its first kept points again fill the rest, and their answers are
    dropped (no gradient reaches them; a hash grid's sparse gradient holds the same rows).

    Returns the field's outputs, each [B, S, ...] in the field's dtype (rgb [B, S, 3], sigma [B, S], ...).
    A skipped sample absorbs nothing, so its colour never reaches a pixel (``render_weights`` gives it
    weight exactly 0).
    """
    index = keep.nonzero(as_tuple=True)  # (ray [N], sample [N])
    n = len(index[0])
    rays, samples = padded_rows(index)  # [P]: the kept, then again
    outputs = ask(field, points[rays, samples], None if viewdirs is None else viewdirs[rays],
                  None if codes is None else codes[rays])  # each [P, ...]
    return scattered(outputs, index, n, keep.shape)


def scattered(outputs: FieldOutputs, index: tuple[Tensor, Tensor], n: int, shape: torch.Size) -> FieldOutputs:
    """The first ``n`` rows of packed ``outputs`` (each [P, ...]) put at ``index`` (ray [n], sample [n]) of
    zeros [B, S, ...] (``shape`` = (B, S))."""
    B, S = shape  # rays, samples
    return each_output(outputs, lambda out: out.new_zeros(B, S, *out.shape[1:]).index_put(index, out[:n]))


def query_thresholded(field: nn.Module, points: Tensor, viewdirs: Tensor, keep: Tensor, lengths: Tensor,
                      alpha_threshold: float, codes: Tensor | None = None) -> tuple[FieldOutputs, Tensor]:
    """``query_packed`` in two stages (nerfacc's ``alpha_thre``): the field's ``positional`` outputs (its density
    and trunk features, ``NeRFField.positional``) at the samples ``keep`` [B, S], then its colour head
    (``coloured``) only at those whose alpha = 1 - exp(-sigma delta) over their interval ``lengths`` [B, S]
    (delta, in distance units) is at least ``alpha_threshold``. The others, like the samples not kept, answer
    zeros: they absorb nothing and their colour reaches no pixel. Each stage's batch is padded as
    ``query_packed``'s (``padded_rows``).

    A sample left out changes a ray's colour and opacity by at most its alpha: below ``alpha_threshold`` each,
    and in all at most 1 - prod(1 - alpha_i) over the samples left out.

    Returns the outputs, each [B, S, ...], and how many samples the colour head evaluated.
    """
    index = keep.nonzero(as_tuple=True)  # (ray [N], sample [N])
    n = len(index[0])
    rays, samples = padded_rows(index)
    positional = field.positional(points[rays, samples])  # each [P, ...]
    sigma = positional.sigma[:n].detach().to(lengths.dtype)
    alpha = -torch.expm1(-sigma * lengths[index])  # [N]
    (chosen,) = (alpha >= alpha_threshold).nonzero(as_tuple=True)  # [M] rows of the packed batch
    m = len(chosen)
    (rows,) = padded_rows((chosen,))  # [Q]
    selected = PositionalOutputs(*(None if out is None else out[rows] for out in positional))
    outputs = ask(field.coloured, selected, viewdirs[rays[rows]], None if codes is None else codes[rays[rows]])
    return scattered(outputs, (index[0][chosen], index[1][chosen]), m, keep.shape), m


def density_query(net: nn.Module) -> Callable[[Tensor, Tensor | None], FieldOutputs]:
    """A density-only network (``DensityField``) as a field the renderer queries: (positions, None)
    -> its ``sigma`` alone; it is queried without directions."""
    return lambda positions, directions: FieldOutputs(rgb=None, sigma=net.density(positions))


def sparsity_loss(sigmas: Tensor, starts: Tensor, ends: Tensor) -> Tensor:
    """An L1 sparsity prior on the densities of a ray's samples, per ray: sum_i sigma_i (end_i - start_i) [B],
    the optical depth the samples [B, S] account for (the quadrature of the integral of sigma along the ray;
    in the spirit of Plenoxels' and SNeRG's sparsity losses on sampled points, L1 rather than their Cauchy
    log(1 + 2 sigma^2), whose gradient vanishes for the faint densities it is to remove).

    Its gradient is the same at every density: it pushes free space's faint floaters to zero as hard as it
    pushes a surface, which the colour loss holds up. Samples not evaluated (sigma 0) add nothing.
    """
    return (sigmas * (ends - starts)).sum(-1)


class VolumeRenderer(nn.Module):
    """Renders rays through its ``sampler`` (``nerfexp.nerf.samplers.Sampler``, the sampling axis's component),
    which places the samples and renders them through the renderer's two steps (``nerfexp.nerf.samplers.Steps``,
    which the renderer is): ``composited`` (a colour field, by name, at samples t) and ``density_weights`` (a
    density-only network's weights at samples t). The renderer builds one field per name of the sampler's
    ``field_names``, under that name (``coarse``, ``fine``).

    The built-in samplers (``nerfexp.nerf.hierarchy``, the ``hierarchical`` flag): hierarchical
    (``HierarchicalSampler``), ``n_coarse`` stratified samples through the coarse field, and ``n_fine`` more from
    its weights, the fine field evaluating all n_coarse + n_fine; without it (``StratifiedSampler``), one field
    evaluates ``n_single`` stratified samples; proposal (mip-NeRF 360, ``nerfexp.nerf.proposal.ProposalSampler``),
    density-only networks resample the ray in rounds, and the one field (named "coarse", as without hierarchy)
    evaluates only the last round's samples.

    With an occupancy ``grid`` (``acceleration=occupancy``) the samples stay where they are, but the
    networks evaluate only those in occupied cells of the grid, packed into one flat batch
    (``query_packed``); the others absorb nothing. With ``grid.early_stop_transmittance`` = eps > 0
    the rays are also marched in ``grid.segments`` consecutive runs of samples: a run is evaluated
    only for the rays that still let through at least eps of the light after the runs before it, so
    the colour a stopped ray loses is at most eps (what could still reach the samples left out), and
    no sample is evaluated twice. With ``grid.alpha_threshold`` > 0, a colour network's samples in
    occupied cells are evaluated in two stages (``query_thresholded``): the density first, then the colour
    head only where the sample's alpha reaches the threshold; the others absorb nothing, as if in an empty
    cell. Whichever sampler runs, its networks are queried through the grid. ``stats`` holds the last call's
    samples per ray evaluated: ``samples_per_ray`` (densities) and ``colour_samples_per_ray`` (colour heads).

    ``sparsity_weight`` > 0 adds, in training, the regularizer ``sparsity``: that weight times the mean over
    the rays of each colour network's ``sparsity_loss`` (an L1 prior on the densities of its samples).

    Args:
        field: builds a field (called once per network of the sampler's ``field_names``), e.g. a partial
            ``NeRFField``.
        sampler: builds the ``Sampler`` (called once, before the fields): a partial ``Sampler`` class, or a
            ``nerfexp.nerf.hierarchy.HierarchyChoice``.
        near, far: ray distance bounds (far: without a contraction, ``ray_far``); background: a key of
            ``BACKGROUNDS``.
        grid: an ``OccupancyGrid``, or None to evaluate every sample.
        appearance: an ``AppearanceEmbedding`` (``appearance=embedding``: a code per training image, which the
            colour fields take, ``nerfexp.nerf.appearance``), or None. With one, the fields are built with its
            ``dim`` (``field(appearance_dim=dim)``), and ``forward`` takes each ray's code.
        contraction: a ``SceneContraction`` for unbounded scenes (``contraction=mipnerf360``), or None. With one,
            the networks and the grid see contracted positions (in its ``box``; the grid's cells are weighed
            by the world lengths they span), and every sampler spaces its samples evenly in t up to where each
            ray leaves the inner region and evenly in disparity beyond it (``Rays.split``). Densities are still
            integrated over world distances, and rays end at the contraction's own far distance.
        sparsity_weight: the weight of the ``sparsity`` regularizer (0: off).
    """

    DOMAINS: ClassVar[dict[str, Rule]] = {
        "near": optional(NEAR, "from the scene"),
        "far": optional(FAR, "from the scene"),
        "background": choice(*BACKGROUNDS),
        "sparsity_weight": LOSS_WEIGHT,
    }
    CONSISTENT: ClassVar[dict[tuple[str, ...], Consistent]] = {
        ("near", "far"): lambda config: (None if config["near"] is None or config["far"] is None
                                         or config["near"] < config["far"]
                                         else "near < far (the rays are sampled between them)"),
        ("sampler", "grid"): lambda config: (None if config["grid"] is not None or not needs_grid(config["sampler"])
                                             else "an occupancy grid (acceleration=occupancy): the sampler places "
                                                  "its samples in the grid's occupied cells"),
    }

    def __init__(self, field: Callable[[], nn.Module], sampler: Callable[[], Sampler], near: float, far: float,
                 background: str = "white", grid: OccupancyGrid | None = None,
                 contraction: SceneContraction | None = None, appearance: AppearanceEmbedding | None = None,
                 sparsity_weight: float = 0.0):
        super().__init__()
        if not sparsity_weight >= 0:
            raise ValueError(f"model.renderer.sparsity_weight: expected a weight >= 0, got {sparsity_weight}")
        self.sparsity_weight = sparsity_weight
        if background not in BACKGROUNDS:
            raise ValueError(f"data.background: expected one of {sorted(BACKGROUNDS)}, got {background!r}")
        # Built first, as a module of the renderer: a sampler's own networks (the proposals') draw their initial
        # weights before the fields', and are saved in checkpoints under ``sampler``.
        self.sampler = sampler()
        if self.sampler.NEEDS_GRID and grid is None:
            raise ValueError(f"model.renderer.sampler: {type(self.sampler).__name__} places its samples in the "
                             "occupancy grid's occupied cells: it needs acceleration=occupancy")
        self.near, self.far = near, far
        self.appearance = appearance
        sized = {} if appearance is None else {"appearance_dim": appearance.dim}  # fields take codes of its size
        self.fine = None  # the final renders' network where the sampler has one (``final_output``)
        for name in self.sampler.field_names:  # "coarse", then "fine": the names checkpoints hold them under
            setattr(self, name, field(**sized))
        self.register_buffer("background", torch.tensor(BACKGROUNDS[background]), persistent=False)
        self.grid = grid
        self.contraction = contraction
        if grid is not None and contraction is not None:
            grid.world_scale = contraction.stretch
        self.stats: dict[str, Tensor | float] = {}
        # training totals, for evaluations_per_ray and colour_evaluations_per_ray
        self._trained = {"rays": 0, "evaluations": 0.0, "colour_evaluations": 0.0}

    @property
    def ray_far(self) -> float:
        """Where rays end: ``far``, or with a contraction its own far distance (``far`` then does nothing)."""
        return self.far if self.contraction is None else self.contraction.far_distance

    @property
    def samples_per_ray(self) -> int:
        """Samples per ray, all networks (the sampler's ``samples_per_ray``)."""
        return self.sampler.samples_per_ray

    @property
    def evaluations_per_ray(self) -> float:
        """Network evaluations per ray (each a density, the position's encoding and the trunk, all networks):
        ``samples_per_ray`` without a grid; with one, the mean over the training rays so far of the samples
        evaluated."""
        if self.grid is None or self._trained["rays"] == 0:
            return self.samples_per_ray
        return float(self._trained["evaluations"]) / self._trained["rays"]

    @property
    def colour_evaluations_per_ray(self) -> float:
        """Colour-head evaluations per ray (the colour networks' samples: not the proposal networks', which have
        no colour): with a grid the mean over the training rays so far, below the density evaluations where
        ``grid.alpha_threshold`` leaves faint samples out; without one, or before training, every colour
        network's samples."""
        if self.grid is None or self._trained["rays"] == 0:
            return self.sampler.colour_samples_per_ray
        return float(self._trained["colour_evaluations"]) / self._trained["rays"]

    def density_fns(self) -> list[Callable[[Tensor], Tensor]]:
        """Each colour network's density (positions [N, 3] -> sigma [N]), for ``OccupancyGrid.update``."""
        return [getattr(self, name).density for name in self.sampler.field_names]

    def _query(self, field: Callable[..., FieldOutputs], points: Tensor,
               viewdirs: Tensor | None, starts: Tensor, ends: Tensor,
               codes: Tensor | None = None,
               valid: Tensor | None = None) -> tuple[FieldOutputs, Tensor | float, Tensor | float]:
        """The field's outputs (each [B, S, ...]; ``sigma`` alone for a density query, whose ``viewdirs`` are
        None) at the points [B, S, 3], ``starts``, ``ends`` [B, S] their intervals in distance units, and the
        samples evaluated, of the density and of the colour (0 for a density query): all of them without a grid,
        else those the grid keeps, marched in segments for early termination, and of those the colour only where
        their alpha reaches ``grid.alpha_threshold`` (see the class docstring). ``codes`` [B, D]: the rays'
        appearance codes, or None. ``valid`` [B, S]: the samples a sampler's ``Spans`` vouch for (all in occupied
        cells), evaluated instead of those the grid keeps."""
        B, S, _ = points.shape  # rays, samples, xyz
        colour = viewdirs is not None
        if self.grid is None:  # one flat batch [B S, 3]: 2-D matrix products, no copies of 3-D activations
            flat_dirs = None if viewdirs is None else viewdirs[:, None, :].expand(B, S, 3).reshape(B * S, 3)
            flat_codes = None if codes is None else codes[:, None, :].expand(B, S, -1).reshape(B * S, -1)
            outputs = ask(field, points.reshape(B * S, 3), flat_dirs, flat_codes)
            return (each_output(outputs, lambda out: out.reshape(B, S, *out.shape[1:])), float(B * S),
                    float(B * S) if colour else 0.0)
        keep = self.grid.occupied_at(points) if valid is None else valid
        eps = self.grid.early_stop_transmittance
        n_segments = 1 if eps == 0 else min(self.grid.segments, S)
        parts, evaluated, coloured = [], 0, 0
        depth_before = starts.new_zeros(B)  # optical depth in front of the segment, no gradient
        for k in range(n_segments):
            segment = slice(k * S // n_segments, (k + 1) * S // n_segments)
            alive = keep[:, segment]
            if eps > 0:
                alive = alive & (torch.exp(-depth_before) >= eps)[:, None]
            outputs, coloured_here = self._query_kept(field, points[:, segment], viewdirs, alive, codes,
                                                      ends[:, segment] - starts[:, segment])
            if k + 1 < n_segments:
                depth_before = depth_before + optical_depths(outputs.sigma.detach().to(starts.dtype),
                                                             starts[:, segment], ends[:, segment]).sum(-1)
            parts.append(outputs)
            evaluated = evaluated + alive.sum()
            coloured = coloured + coloured_here
        if n_segments == 1:
            return parts[0], evaluated, coloured
        joined = (None if column[0] is None else torch.cat(column, 1) for column in zip(*parts))
        return FieldOutputs(*joined), evaluated, coloured

    def _query_kept(self, field: Callable[..., FieldOutputs], points: Tensor, viewdirs: Tensor | None,
                    keep: Tensor, codes: Tensor | None, lengths: Tensor) -> tuple[FieldOutputs, Tensor | int]:
        """The field's outputs [B, S, ...] at the samples ``keep`` [B, S] of ``points`` [B, S, 3] (intervals
        ``lengths`` [B, S] long), and how many the colour head evaluated: ``query_packed``, or for a colour query
        with a positive ``grid.alpha_threshold`` ``query_thresholded``."""
        if viewdirs is None or self.grid.alpha_threshold == 0:
            return query_packed(field, points, viewdirs, keep, codes), (0 if viewdirs is None else keep.sum())
        return query_thresholded(field, points, viewdirs, keep, lengths, self.grid.alpha_threshold, codes)

    def field_positions(self, points: Tensor) -> Tensor:
        """World positions [..., 3] as the networks and the grid take them: contracted where the renderer has a
        contraction, else unchanged."""
        return points if self.contraction is None else self.contraction(points)

    def _samples(self, rays: Rays, t: Tensor, spans: Spans | None = None) -> tuple[Tensor, ...]:
        """The sample points [B, S, 3] of rays o + t d at t [B, S] (as the networks take them:
        ``field_positions``), and the intervals they stand for (``spans``' where given, else ``intervals``, the
        last ending at far [B]): in units of t, ``t_starts``, ``t_ends`` [B, S], and in distance, ``starts``,
        ``ends`` [B, S] (an interval [t_i, t_{i+1}] is (t_{i+1} - t_i) |d| long)."""
        points = self.field_positions(rays.origins[:, None, :] + rays.directions[:, None, :] * t[..., None])
        lengths = torch.linalg.vector_norm(rays.directions, dim=-1, keepdim=True)  # [B, 1]
        t_starts, t_ends = intervals(t, rays.far) if spans is None else (spans.t_starts, spans.t_ends)
        return points, t_starts, t_ends, t_starts * lengths, t_ends * lengths

    def density_weights(self, network: nn.Module, rays: Rays, t: Tensor) -> tuple[Tensor, Tensor | float]:
        """A density-only network's interval weights [B, S] at samples t [B, S] of ``rays``, and the samples
        it evaluated (``nerfexp.nerf.samplers.Steps``)."""
        points, _, _, starts, ends = self._samples(rays, t)
        outputs, evaluated, _ = self._query(density_query(network), points, None, starts, ends)
        weights, _ = render_weights(outputs.sigma.to(t.dtype), starts, ends)
        return weights, evaluated

    def composited(self, name: str, rays: Rays, t: Tensor, spans: Spans | None = None) -> dict[str, Tensor]:
        """The colour field ``name`` (``coarse``, ``fine``: one of the sampler's ``field_names``) at samples t
        [B, S] of ``rays`` (``render_at``; ``nerfexp.nerf.samplers.Steps``)."""
        return self.render_at(getattr(self, name), rays, t, spans)

    def render_at(self, field: nn.Module, rays: Rays, t: Tensor, spans: Spans | None = None) -> dict[str, Tensor]:
        """Query ``field`` at samples t [B, S] of ``rays``; each sample stands for its interval (``spans``' where
        given: only their ``valid`` samples are evaluated). The output (see ``forward``) also holds ``evaluated``,
        the samples the field evaluated.

        The field sees the unit ``viewdirs`` [B, 3]. A field that also answers per-sample ``penalties``
        [B, S, P] (``penalty_names``, e.g. Ref-NeRF's normals, ``nerfexp.nerf.reflection``) has them composited
        with the rendering weights and averaged over the rays into ``regularizers`` {name: value}.
        """
        points, t_starts, t_ends, starts, ends = self._samples(rays, t, spans)
        outputs, evaluated, coloured = self._query(field, points, rays.viewdirs, starts, ends, rays.appearance,
                                                   None if spans is None else spans.valid)
        # Rendering runs in the rays' precision whatever the network's: under bf16 autocast the field
        # answers in bf16 (8 significant bits), too coarse for exp/cumsum of optical depths.
        rgbs, sigmas = outputs.rgb.to(t.dtype), outputs.sigma.to(t.dtype)
        weights, _ = render_weights(sigmas, starts, ends)
        out = composite(weights, rgbs, t, self.background, self.ray_far)
        out.update(weights=weights, t_starts=t_starts, t_ends=t_ends, evaluated=evaluated, coloured=coloured)
        regularizers = {}
        if outputs.penalties is not None:
            per_ray = (weights[..., None] * outputs.penalties.to(t.dtype)).sum(-2).mean(0)  # [P]
            regularizers.update(zip(field.penalty_names, per_ray.unbind(), strict=True))
        if self.sparsity_weight > 0 and torch.is_grad_enabled():
            regularizers["sparsity"] = self.sparsity_weight * sparsity_loss(sigmas, starts, ends).mean()
        if regularizers:
            out["regularizers"] = regularizers
        return out

    def forward(self, origins: Tensor, directions: Tensor, deterministic: bool,
                viewdirs: Tensor | None = None, codes: Tensor | None = None) -> dict[str, dict[str, Tensor]]:
        """Render rays o + t d, ``origins``, ``directions`` [B, 3], for t in [near, far].

        Directions need not be unit vectors (NDC rays' are not): densities are integrated over the
        length t |d| in the space the points o + t d live in (NDC space for NDC rays, as in the
        paper's code). The field's view direction is ``viewdirs`` [B, 3] (unit; for NDC rays the
        world direction), by default the unit ``directions``. ``codes`` [B, D]: each ray's appearance code,
        only where the renderer has an ``appearance`` embedding (None there: its ``test_code`` for every ray,
        the appearance of an image it was not trained on).

        Returns {"coarse": out, "fine": out} (the sampler's ``field_names``: only "coarse" without hierarchy or
        with proposals), each out holding ``rgb`` [B, 3], ``depth`` [B] (in units of t), ``opacity`` [B],
        ``weights``, ``t_starts``, ``t_ends`` [B, S], and ``regularizers`` {name: scalar} where its network or
        the proposals add losses (only while gradients are enabled, for the proposals' ones).
        """
        B, _ = origins.shape  # rays, xyz
        if viewdirs is None:
            lengths = torch.linalg.vector_norm(directions, dim=-1, keepdim=True)
            viewdirs = directions / lengths.clamp_min(torch.finfo(lengths.dtype).tiny)
        near = torch.full((B,), self.near, dtype=origins.dtype, device=origins.device)
        far = torch.full_like(near, self.ray_far)
        split = None if self.contraction is None else self.contraction.ray_split(origins, directions)
        if codes is not None and self.appearance is None:
            raise ValueError("VolumeRenderer: appearance codes given to a renderer without appearance=embedding")
        if codes is None and self.appearance is not None:  # an image not trained on: the embedding's test code
            codes = self.appearance.test_code().expand(B, -1)
        rays = Rays(origins, directions, viewdirs, near, far, split, codes)
        outputs = self.sampler.render(rays, self, deterministic)
        self._count(outputs, B)
        return outputs

    def _count(self, outputs: dict[str, dict], n_rays: int) -> None:
        """``stats`` of the call (samples per ray evaluated, all networks: ``samples_per_ray`` of the density,
        ``colour_samples_per_ray`` of the colour heads), pulled out of ``outputs`` (left on the device: no host
        copy), and the training totals."""
        evaluated = sum(out.pop("evaluated") for out in outputs.values()) / n_rays
        coloured = sum(out.pop("coloured") for out in outputs.values()) / n_rays
        self.stats = {"samples_per_ray": evaluated, "colour_samples_per_ray": coloured}
        if self.training and self.grid is not None:
            self._trained["rays"] += n_rays
            self._trained["evaluations"] = self._trained["evaluations"] + evaluated * n_rays
            self._trained["colour_evaluations"] = self._trained["colour_evaluations"] + coloured * n_rays
