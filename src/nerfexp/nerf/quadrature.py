"""Volume rendering by quadrature along rays.

Conventions (all functions here): a ray is cut into S intervals [t_starts, t_ends], each [..., S],
sorted along the ray; ``sigmas`` [..., S] is the density in each interval. ``weights`` [..., S] are
the probabilities that the ray terminates in each interval; they sum to the opacity, <= 1.
"""

import torch
from torch import Tensor


def optical_depths(sigmas: Tensor, t_starts: Tensor, t_ends: Tensor) -> Tensor:
    """Optical depth tau = sigma * delta of each interval, delta = t_ends - t_starts: [..., S].

    An interval absorbs nothing when its density or its length is zero, whatever the other factor:
    tau is exactly 0 there, never ``0 * inf = nan`` (an empty background interval of infinite length,
    or an infinite density over a zero-width interval). An infinite interval of positive density is
    opaque (tau = inf), and its tau does not depend on sigma, so no ``0 * inf`` reaches the gradient.
    A product too large for the dtype becomes inf, which is the right limit too.

    Args: sigmas [..., S] >= 0 (may be inf), t_starts <= t_ends [..., S] (t_ends may be inf).
    """
    deltas = t_ends - t_starts
    infinite = torch.isinf(deltas)
    finite_product = sigmas * torch.where(infinite, 0, deltas)  # the gradient sees only finite lengths
    tau = torch.where(infinite, torch.inf, finite_product)
    return torch.where((sigmas == 0) | (deltas == 0), 0, tau)  # a NaN density stays NaN, for the guards to see


def render_weights(sigmas: Tensor, t_starts: Tensor, t_ends: Tensor) -> tuple[Tensor, Tensor]:
    """Quadrature weights w_i = T_i (1 - exp(-sigma_i delta_i)), and transmittance T_i.

    T_i = exp(-sum_{j<i} sigma_j delta_j), delta_i = t_ends_i - t_starts_i.
    Safe by construction, with no additive epsilon anywhere:
    - tau comes from ``optical_depths`` (0 for empty or zero-width intervals, inf for opaque ones);
    - alpha is ``-expm1(-tau)``: exact for small tau, where ``1 - exp(-tau)`` cancels to 0 in float32
      below tau = 6e-8, and exactly 1 at tau = inf;
    - the transmittance is the exponential of an exclusive cumulative sum of tau (log space), not a
      cumulative product of ``1 - alpha``: the sum of non-negative terms cannot go negative or NaN, an
      opaque interval gives T = 0 after it (never inf - inf), and there is no ``1 - alpha + 1e-10``
      to bias every weight;
    - so the weights are in [0, 1] and sum to 1 - T_S (up to rounding) without any clamp, and the
      gradients are finite: d alpha / d tau = exp(-tau) and d T / d tau = -T are bounded by 1.

    Args: sigmas, t_starts, t_ends: [..., S], sigmas >= 0 (inf allowed), t_ends may be inf.
    Returns: (weights [..., S], transmittance [..., S]).

    Example: one interval of density 1 and length ln 2 gives weight 1/2:
    >>> render_weights(torch.tensor([1.0]), torch.tensor([0.0]), torch.tensor([0.6931472]))[0]
    tensor([0.5000])
    """
    tau = optical_depths(sigmas, t_starts, t_ends)
    alphas = -torch.expm1(-tau)
    tau_before = torch.cat([torch.zeros_like(tau[..., :1]), torch.cumsum(tau[..., :-1], dim=-1)], dim=-1)
    transmittance = torch.exp(-tau_before)
    return transmittance * alphas, transmittance


def composite(weights: Tensor, rgbs: Tensor, t: Tensor, background: Tensor, far: float) -> dict[str, Tensor]:
    """Colour, depth, disparity and opacity of rays from their interval weights.

    Args:
        weights: [..., S] from ``render_weights``.
        rgbs: [..., S, 3] colour in each interval.
        t: [..., S] the sample position of each interval.
        background: [3] colour seen where the ray is not absorbed.
        far: depth reported for rays that absorb nothing (> 0).
    Returns: dict of ``rgb`` [..., 3], ``opacity`` [...] (sum of weights), ``depth`` [...] (expected
    termination distance of the absorbed part) and ``disparity`` [...] = 1 / depth.

    Depth divides the weights by the opacity only where it is positive (the division is guarded by
    selection, not by an epsilon, so a barely absorbing ray keeps its true depth instead of one pulled towards 0);
    a ray that absorbs nothing is reported at ``far``, so its disparity is 1 / far, not inf or nan.
    A depth of exactly 0 (a ray starting inside a surface) has disparity inf, its true value.
    """
    opacity = weights.sum(-1)
    rgb = (weights[..., None] * rgbs).sum(-2) + (1 - opacity[..., None]) * background
    absorbed = opacity > 0
    # each weight's share of the opacity, taken before it meets t: denormal weights times t lose their
    # ratio (one weight of 1.4e-45 at t = 1.5 gave depth 2 as sum(w t) / sum(w)); shares lie in [0, 1]
    shares = weights / torch.where(absorbed, opacity, 1)[..., None]
    depth = torch.where(absorbed, (shares * t).sum(-1), far)
    return {"rgb": rgb, "depth": depth, "disparity": torch.reciprocal(depth), "opacity": opacity}
