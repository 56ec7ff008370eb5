"""The sampling axis: where along each ray the fields are evaluated, and by which networks (nerfacc's
``AbstractTransEstimator``: one interface for every way of placing samples).

A ``Sampler`` places samples on a batch of ``Rays`` and renders them through the two ``Steps`` its caller (the
renderer, ``nerfexp.nerf.volume_renderer.VolumeRenderer``) provides: ``composited`` (a colour network, by name, at
samples t: its composited output) and ``density_weights`` (a density-only network's interval weights at samples t).
The sampler knows nothing else of the renderer. Both steps query the networks through the occupancy grid where
there is one: the grid's skipping is a component beside the samplers, applied to whichever runs. The samplers:
``HierarchicalSampler`` (the paper's coarse + fine), ``StratifiedSampler`` (one network) and
``nerfexp.nerf.proposal.ProposalSampler`` (mip-NeRF 360's proposal networks); ``nerfexp.nerf.hierarchy`` builds
the one the ``hierarchical`` flag names.

Conventions: ``t`` are sample positions along the rays [B, S], sorted, in units of the rays' directions; the
renderer's outputs are {network name: output} with the names of ``field_names``.
"""

import importlib
from collections.abc import Mapping
from typing import ClassVar, NamedTuple, Protocol

import torch
from torch import Tensor, nn

from nerfexp.domains import Applies, Rule
from nerfexp.nerf.sampling import (
    dilate_weights,
    disparity_fraction,
    disparity_spaced,
    resampling_bins,
    sample_pdf,
    stratified_samples,
)


class Rays(NamedTuple):
    """A batch of B rays o + t d for t in [near, far]."""

    origins: Tensor  # [B, 3]
    directions: Tensor  # [B, 3], not necessarily unit (NDC rays' are not)
    viewdirs: Tensor  # [B, 3] unit: the view direction the colour networks see
    near: Tensor  # [B]
    far: Tensor  # [B]
    # [B] or None: where samples stop being spaced evenly in t and are spaced evenly in disparity (a contracted,
    # unbounded scene's rays leaving its inner region: ``disparity_spaced``); None: evenly in t up to far
    split: Tensor | None = None
    # [B, D] or None: each ray's appearance code, which the colour networks take (``nerfexp.nerf.appearance``)
    appearance: Tensor | None = None


def first_samples(rays: Rays, n_samples: int, deterministic: bool) -> Tensor:
    """``n_samples`` stratified samples t [B, n_samples] of ``rays``: one in each of equal bins of [near, far],
    or, where the rays have a ``split``, of the fraction s of ``disparity_spaced`` (evenly in t to the split,
    evenly in disparity beyond)."""
    if rays.split is None:
        return stratified_samples(rays.near, rays.far, n_samples, deterministic)
    s = stratified_samples(torch.zeros_like(rays.near), torch.ones_like(rays.far), n_samples, deterministic)
    return disparity_spaced(s, rays.near, rays.split, rays.far)


def resample(rays: Rays, t: Tensor, weights: Tensor, n_samples: int, deterministic: bool) -> Tensor:
    """``n_samples`` samples [B, n_samples] of ``rays`` drawn from the weights [B, S] of the intervals of samples
    t [B, S] (``resampling_bins``, dilated by one interval: ``dilate_weights``). Where the rays have a ``split``,
    the weights are spread evenly over their intervals in the fraction s of ``disparity_spaced``, not in t
    (mip-NeRF 360 resamples in s: a far interval in t is long, and its mass lies at the near end in
    disparity)."""
    bins, weights = resampling_bins(t, rays.near, rays.far), dilate_weights(weights)
    if rays.split is None:
        return sample_pdf(bins, weights, n_samples, deterministic)
    s = sample_pdf(disparity_fraction(bins, rays.near, rays.split, rays.far), weights, n_samples, deterministic)
    return disparity_spaced(s, rays.near, rays.split, rays.far)


class Spans(NamedTuple):
    """Samples' intervals given by the sampler rather than made from the samples (``intervals``: each sample up to
    the next): ``t_starts``, ``t_ends`` [B, S], in units of t, and ``valid`` [B, S] (bool), the samples that exist;
    the others are zero-length intervals, never evaluated (a march's rows, ``nerfexp.nerf.marching``)."""

    t_starts: Tensor
    t_ends: Tensor
    valid: Tensor


class Steps(Protocol):
    """What a sampler asks of its caller (the renderer): its two steps, each querying the networks through the
    occupancy grid where there is one, and the renderer's ``grid`` (an ``OccupancyGrid``, or None) and
    ``contraction`` (a ``SceneContraction``, or None), for a sampler that places its samples by them."""

    grid: nn.Module | None
    contraction: nn.Module | None

    def composited(self, name: str, rays: Rays, t: Tensor, spans: Spans | None = None) -> dict[str, Tensor]:
        """The colour network ``name`` (one of the sampler's ``field_names``) at samples t [B, S] of ``rays``,
        each standing for its interval (``spans``' where given, whose ``valid`` samples alone are evaluated: the
        sampler vouches that they lie in occupied cells; else each sample up to the next): the renderer's output
        (``VolumeRenderer.forward``: ``rgb`` [B, 3], ``depth``, ``opacity`` [B], ``weights``, ``t_starts``,
        ``t_ends`` [B, S], ...), also holding ``evaluated`` and ``coloured``, the samples whose density and colour
        the network evaluated."""

    def density_weights(self, network: nn.Module, rays: Rays, t: Tensor) -> tuple[Tensor, Tensor | float]:
        """A density-only network's (``network.density``: positions [N, 3] -> sigma [N]) interval weights
        [B, S] at samples t [B, S] of ``rays``, and the samples it evaluated."""


class Sampler(nn.Module):
    """Places samples on rays and renders them: the sampling axis's component.

    ``field_names``: the colour networks it renders with (the renderer builds one field for each, under that name,
    and its outputs carry the same names). ``samples_per_ray``: samples per ray, all networks together, before
    any are skipped. ``render``: the renderer's outputs for a batch of rays, through the renderer's ``Steps``.
    ``DOMAINS`` and ``APPLIES`` declare its constructor's settings (``nerfexp.domains``), where a user configures
    it, and ``SAMPLES_PER_RAY`` (a staticmethod: its config, resolved as plain data -> (network evaluations per
    ray, the argument names that set them)) what the settings check's activation-memory estimate counts.
    ``NEEDS_GRID``: whether it places its samples by the renderer's occupancy grid (``Steps.grid``), which the
    renderer then requires (``needs_grid``).
    """

    DOMAINS: ClassVar[dict[str, Rule]] = {}
    APPLIES: ClassVar[dict[str, Applies]] = {}
    field_names: ClassVar[tuple[str, ...]] = ("coarse",)
    NEEDS_GRID: ClassVar[bool] = False  # whether it places its samples by the renderer's occupancy grid

    @property
    def samples_per_ray(self) -> int:
        raise NotImplementedError

    def kernels(self) -> tuple[str, ...]:
        """The fused kernels (``nerfexp.kernels``) its sampling runs, built before the training clock starts; by
        default none."""
        return ()

    @property
    def colour_samples_per_ray(self) -> int:
        """The samples per ray of the colour networks (``field_names``), before any are skipped: all of them,
        unless the sampler has networks without colour."""
        return self.samples_per_ray

    def render(self, rays: Rays, steps: Steps, deterministic: bool) -> dict[str, dict[str, Tensor]]:
        """{name: the renderer's output} for each of ``field_names`` (``Steps.composited``), each still holding
        ``evaluated`` and ``coloured``, the samples its networks evaluated, of the density and of the colour (the
        renderer counts them). ``deterministic``: evenly spaced samples instead of jittered ones."""
        raise NotImplementedError


def needs_grid(section: Mapping) -> bool:
    """Whether the sampler a config's section builds (its ``_target_``, resolved as plain data) declares
    ``NEEDS_GRID``; False for a section whose class does not say (``HierarchyChoice``: the paper's samplers)."""
    target = section.get("_target_") if isinstance(section, Mapping) else None
    if not isinstance(target, str) or "." not in target:
        return False
    module, _, name = target.rpartition(".")
    try:
        cls = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError):  # the settings check names a target that cannot be found
        return False
    return bool(getattr(cls, "NEEDS_GRID", False))


class HierarchicalSampler(Sampler):
    """The paper's: ``n_coarse`` stratified samples through the coarse field; its weights, dilated by one interval
    (``dilate_weights``) as a piecewise-constant PDF over the coarse intervals, give ``n_fine`` more samples by
    inverse-transform sampling; the fine field evaluates all n_coarse + n_fine."""

    field_names = ("coarse", "fine")

    def __init__(self, n_coarse: int, n_fine: int):
        super().__init__()
        self.n_coarse = n_coarse
        self.n_fine = n_fine

    @staticmethod
    def SAMPLES_PER_RAY(config: Mapping) -> tuple[int, tuple[str, ...]]:
        return config["n_coarse"] + (config["n_coarse"] + config["n_fine"]), ("n_coarse", "n_fine")

    @property
    def samples_per_ray(self) -> int:
        return self.SAMPLES_PER_RAY(vars(self))[0]

    def render(self, rays: Rays, steps: Steps, deterministic: bool) -> dict[str, dict[str, Tensor]]:
        t_coarse = first_samples(rays, self.n_coarse, deterministic)
        coarse = steps.composited("coarse", rays, t_coarse)
        t_fine = resample(rays, t_coarse, coarse["weights"], self.n_fine, deterministic)
        t_all = torch.sort(torch.cat([t_coarse, t_fine], -1), -1).values
        return {"coarse": coarse, "fine": steps.composited("fine", rays, t_all)}


class StratifiedSampler(Sampler):
    """One field evaluates ``n_samples`` stratified samples (the paper's "No Hierarchical" row: 256, the same
    network evaluations per ray as 64 + 192)."""

    def __init__(self, n_samples: int):
        super().__init__()
        self.n_samples = n_samples

    @staticmethod
    def SAMPLES_PER_RAY(config: Mapping) -> tuple[int, tuple[str, ...]]:
        return config["n_samples"], ("n_samples",)

    @property
    def samples_per_ray(self) -> int:
        return self.SAMPLES_PER_RAY(vars(self))[0]

    def render(self, rays: Rays, steps: Steps, deterministic: bool) -> dict[str, dict[str, Tensor]]:
        t = first_samples(rays, self.n_samples, deterministic)
        return {"coarse": steps.composited("coarse", rays, t)}
