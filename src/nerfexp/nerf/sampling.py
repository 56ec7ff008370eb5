"""Where along each ray the field is evaluated.

Conventions: ``t`` are sample distances along unit-direction rays, [..., S], sorted. ``bins`` are
interval edges [..., S+1] and ``weights`` [..., S] the mass of each interval (sums need not be 1).
"""

import torch
from torch import Tensor


def stratified_samples(near: Tensor, far: Tensor, n_samples: int, deterministic: bool,
                       generator: torch.Generator | None = None) -> Tensor:
    """One sample in each of ``n_samples`` equal bins of [near, far]: [..., n_samples].

    Jittered uniformly inside its bin in training; the bin's midpoint when ``deterministic``.
    near, far: [...].
    """
    edges = torch.linspace(0, 1, n_samples + 1, dtype=near.dtype, device=near.device)
    if deterministic:
        u = torch.full((*near.shape, n_samples), 0.5, dtype=near.dtype, device=near.device)
    else:
        u = torch.rand((*near.shape, n_samples), dtype=near.dtype, device=near.device, generator=generator)
    fractions = edges[:-1] + u * (edges[1:] - edges[:-1])
    return torch.lerp(near[..., None], far[..., None], fractions)


def linear_share(near: Tensor, split: Tensor, far: Tensor) -> Tensor:
    """The share of the unit interval [0, 1] of ``disparity_spaced`` that maps linearly onto [near, split]:
    1/2 where near < split < far (mip-NeRF 360's and nerfacto's), 1 where split >= far (the ray never leaves
    the inner region before far), 0 where split <= near (it starts outside). [...]"""
    return torch.where(split >= far, 1.0, torch.where(split > near, 0.5, 0.0)).to(near.dtype)


def disparity_spaced(s: Tensor, near: Tensor, split: Tensor, far: Tensor) -> Tensor:
    """Distances t [..., S] for fractions s [..., S] in [0, 1] of rays (near, split, far [...]): spaced evenly in
    t from near to split over the first ``linear_share`` h of s, then evenly in disparity 1 / t from split to far
    (mip-NeRF 360's sampling of unbounded scenes; nerfacto's ``UniformLinDispPiecewiseSampler`` splits at t = 1).

    With a = max(near, split) and u = (s - h) / (1 - h) the disparity part is t = a far / ((1 - u) far + u a),
    written so that no disparity (1 / 0) is formed: u = 0 gives a, u = 1 gives far. Monotone; its inverse is
    ``disparity_fraction``."""
    near, split, far = near[..., None], split[..., None], far[..., None]
    share = linear_share(near, split, far)
    start = torch.maximum(near, split).minimum(far)
    linear = torch.lerp(near, start, s / torch.where(share == 0, 1, share))
    u = ((s - share) / torch.where(share == 1, 1, 1 - share)).clamp(0, 1)
    disparity = start * far / ((1 - u) * far + u * start)
    return torch.where(s <= share, linear, disparity)


def disparity_fraction(t: Tensor, near: Tensor, split: Tensor, far: Tensor) -> Tensor:
    """The inverse of ``disparity_spaced``: the fractions s [..., S] in [0, 1] of distances t [..., S] in
    [near, far] of rays (near, split, far [...]). The disparity part u = far (t - a) / (t (far - a)) divides
    by t >= a > 0 and far > a, where it is selected."""
    near, split, far = near[..., None], split[..., None], far[..., None]
    share = linear_share(near, split, far)
    start = torch.maximum(near, split).minimum(far)
    span = start - near
    linear = share * (t - near) / torch.where(span == 0, 1, span)
    outer = t > start
    denominator = torch.where(outer, t * (far - start), 1)
    u = torch.where(outer, far * (t - start) / denominator, 0)
    return torch.where(outer, share + (1 - share) * u, linear).clamp(0, 1)


def intervals(t: Tensor, far: Tensor) -> tuple[Tensor, Tensor]:
    """The interval each sample stands for, as in the paper: [t_i, t_{i+1}], the last ending at ``far``.

    The density at t_i fills the gap up to the next sample. This is the right side to err on for
    surfaces: the last empty sample before a surface fills the gap up to the first sample inside it,
    so a surface starts where it is first sampled (within the fine samples' spacing), whereas
    splitting gaps at midpoints would move every surface forward by half the coarse spacing.
    The paper's last interval is 1e10 long, which makes the last sample opaque whatever its
    density; ending it at ``far`` lets a field with small positive density in empty space (softplus)
    still show the background. t: [..., S] sorted, far: [...]. Returns (t_starts, t_ends), each [..., S].
    """
    return t, torch.cat([t[..., 1:], far[..., None]], -1)


def resampling_bins(t: Tensor, near: Tensor, far: Tensor) -> Tensor:
    """The PDF bins [B, S+1] to resample from the weights of the intervals of samples t [B, S]: those
    intervals, the first reaching back to ``near`` [B] (the first sample lies up to one spacing past near,
    and what lies before it must still be reachable by the new samples, else a density at near is lost
    however many are drawn), the last ending at ``far`` [B]."""
    return torch.cat([near[:, None], t[:, 1:], far[:, None]], -1)


def dilate_weights(weights: Tensor) -> Tensor:
    """Each interval's weight raised to the largest of its own and its two neighbours': [..., S].

    With samples standing for [t_i, t_{i+1}], a surface first seen at sample k enters somewhere in
    [t_{k-1}, t_k], an interval whose own weight is zero. Resampling the raw weights (or the paper's
    midpoint bins) never puts fine samples there, so the surface stays displaced by up to one coarse
    spacing however many fine samples are drawn; the dilated weights cover it, and the rendered
    opacity converges as the fine samples grow (``tests/nerf/test_volume_renderer.py``).
    """
    zero = torch.zeros_like(weights[..., :1])
    before = torch.cat([zero, weights[..., :-1]], -1)
    after = torch.cat([weights[..., 1:], zero], -1)
    return torch.maximum(weights, torch.maximum(before, after))


def sample_pdf(bins: Tensor, weights: Tensor, n_samples: int, deterministic: bool,
               generator: torch.Generator | None = None) -> Tensor:
    """Inverse-transform samples of the piecewise-constant density with mass ``weights`` on ``bins``.

    Args:
        bins: [..., S+1] sorted interval edges.
        weights: [..., S] non-negative masses; all zero means uniform.
        n_samples: samples per ray.
        deterministic: evenly spaced quantiles u_k = (k + 1/2) / n instead of stratified ones.
    Returns: sorted samples [..., n_samples] inside [bins[..., 0], bins[..., -1]], detached (no
    gradient flows through sample positions).

    Stratified quantiles: u_k = (k + xi_k) / n, xi_k uniform in [0, 1), one in each n-th of the CDF,
    as ``stratified_samples`` does along the ray. Each u_k is still uniform over [0, 1) when k is
    drawn at random, so the set of samples follows the PDF as n sorted uniform u (the paper's code)
    would, but a bin of mass w always receives n w samples, less than 2 off, where sorted uniform u
    give n w +- sqrt(n w): the fine samples cover the surface instead of clumping, and the rendered
    colours vary less from step to step (measured in docs/departures.md).

    Safe by construction: the CDF starts at exactly 0 and ends at exactly 1 (x / x == 1 in floating
    point), so every u in [0, 1) finds a bin (u is kept below 1 where (k + xi) / n rounds up to it);
    intervals of zero mass are never selected (``searchsorted(right=True)`` skips them), so the in-bin
    fraction divides by a positive mass; the fraction is clamped to [0, 1] and ``lerp`` stays inside
    the bin, also a zero-width one. No epsilon is added to the weights (the common ``weights + 1e-5``
    puts samples in empty space and biases every PDF); all-zero weights are uniform by selection. A nan
    weight gives nan samples, so a failed coarse pass is seen rather than silently resampled uniformly.
    """
    bins, weights = bins.detach(), weights.detach()
    total = weights.sum(-1, keepdim=True)
    weights = torch.where(total == 0, torch.ones_like(weights), weights)  # no mass: uniform (a nan stays nan)
    cdf = torch.cumsum(weights, -1)
    cdf = torch.cat([torch.zeros_like(cdf[..., :1]), cdf / cdf[..., -1:]], -1)  # [..., S+1], x / x == 1 exactly
    shape = (*cdf.shape[:-1], n_samples)
    if deterministic:
        u = (torch.arange(n_samples, dtype=cdf.dtype, device=cdf.device) + 0.5) / n_samples
        u = u.expand(shape).contiguous()
    else:
        jitter = torch.rand(shape, dtype=cdf.dtype, device=cdf.device, generator=generator)
        u = (torch.arange(n_samples, dtype=cdf.dtype, device=cdf.device) + jitter) / n_samples
        u = u.clamp(max=1 - torch.finfo(u.dtype).eps / 2)  # the float below 1: (n - 1 + xi) / n can round to 1
    n_bins = weights.shape[-1]
    index = torch.searchsorted(cdf, u, right=True).clamp(1, n_bins)  # cdf[index-1] <= u < cdf[index]
    cdf_lo, cdf_hi = cdf.gather(-1, index - 1), cdf.gather(-1, index)
    bin_lo, bin_hi = bins.gather(-1, index - 1), bins.gather(-1, index)
    mass = cdf_hi - cdf_lo
    fraction = torch.where(mass == 0, 0, (u - cdf_lo) / torch.where(mass == 0, 1, mass))  # nan stays nan
    return torch.lerp(bin_lo, bin_hi, fraction.clamp(0, 1))
