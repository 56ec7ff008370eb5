"""Volume rendering by quadrature along rays.

Conventions (all functions here): a ray is cut into S intervals [t_starts, t_ends], each [..., S],
sorted along the ray; ``sigmas`` [..., S] is the density in each interval. ``weights`` [..., S] are
the probabilities that the ray terminates in each interval; they sum to the opacity, <= 1.
"""

import torch
from torch import Tensor


def render_weights(sigmas: Tensor, t_starts: Tensor, t_ends: Tensor) -> tuple[Tensor, Tensor]:
    """Quadrature weights w_i = T_i (1 - exp(-sigma_i delta_i)), and transmittance T_i.

    T_i = exp(-sum_{j<i} sigma_j delta_j), delta_i = t_ends_i - t_starts_i.
    Safe by construction: alpha is ``-expm1(-tau)`` (exact for small optical depth tau, where
    ``1 - exp(-tau)`` cancels), and the transmittance is the exponential of an exclusive cumulative
    sum taken in log space, so an opaque interval (tau = inf) gives T = 0 after it, never inf - inf.

    Args: sigmas, t_starts, t_ends: [..., S], sigmas >= 0.
    Returns: (weights [..., S], transmittance [..., S]).

    Example: one interval of density 1 and length ln 2 gives weight 1/2:
    >>> render_weights(torch.tensor([1.0]), torch.tensor([0.0]), torch.tensor([0.6931472]))[0]
    tensor([0.5000])
    """
    tau = sigmas * (t_ends - t_starts)  # optical depth of each interval
    alphas = -torch.expm1(-tau)
    tau_before = torch.cat([torch.zeros_like(tau[..., :1]), torch.cumsum(tau[..., :-1], dim=-1)], dim=-1)
    transmittance = torch.exp(-tau_before)
    return transmittance * alphas, transmittance


def composite(weights: Tensor, rgbs: Tensor, t: Tensor, background: Tensor, far: float) -> dict[str, Tensor]:
    """Colour, depth and opacity of rays from their interval weights.

    Args:
        weights: [..., S] from ``render_weights``.
        rgbs: [..., S, 3] colour in each interval.
        t: [..., S] the sample position of each interval.
        background: [3] colour seen where the ray is not absorbed.
        far: depth reported for rays that absorb nothing.
    Returns: dict of ``rgb`` [..., 3], ``depth`` [...] (expected termination distance of the absorbed
    part, ``far`` where nothing is absorbed) and ``opacity`` [...] (sum of weights).
    """
    opacity = weights.sum(-1)
    rgb = (weights[..., None] * rgbs).sum(-2) + (1 - opacity[..., None]) * background
    absorbed = opacity > 0
    depth_sum = (weights * t).sum(-1)
    depth = torch.where(absorbed, depth_sum / torch.where(absorbed, opacity, 1), far)
    return {"rgb": rgb, "depth": depth, "opacity": opacity}
