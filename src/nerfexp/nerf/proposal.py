"""Proposal sampling (mip-NeRF 360, Barron et al., CVPR 2022; the sampler of nerfstudio's nerfacto).

Small density-only networks resample each ray in rounds: the first sees stratified samples, each next
one samples the histogram of the weights of the one before (dilated by one interval, as the hierarchy's
coarse weights are: ``nerfexp.nerf.sampling.dilate_weights``), and the NeRF evaluates only the last
round's samples. The proposals learn no colour: the interlevel loss trains each to bound the NeRF's
weights from above, interval by interval, so its histogram puts samples wherever the NeRF absorbs light.

Conventions: ``edges`` [..., S+1] are sorted interval edges along the ray and ``weights`` [..., S] the
mass of each interval (a step function of t whose integral over an interval is its weight).
"""

from collections.abc import Callable, Mapping, Sequence

import torch
from torch import Tensor, nn

from nerfexp.domains import COUNT, LOSS_WEIGHT, LOSS_WEIGHT_LIMIT, real
from nerfexp.nerf.samplers import Rays, Sampler, Steps, first_samples, resample
from nerfexp.nerf.sampling import disparity_fraction, resampling_bins


def outer_bound(edges: Tensor, proposal_edges: Tensor, proposal_weights: Tensor) -> Tensor:
    """For each interval [edges_i, edges_{i+1}]: the sum of the proposal's weights over every proposal
    interval that overlaps it (mip-NeRF 360's bound(t_hat, w_hat, T_i), eq. 12): [..., S].

    Interval j of the proposal overlaps i when proposal_edges_j < edges_{i+1} and proposal_edges_{j+1} > edges_i,
    so the overlapping j run from the number of proposal intervals ending at or before edges_i to the number
    starting before edges_{i+1}; with C the proposal's cumulative weights (C_0 = 0), the bound is
    C[that second number] - C[that first one], never negative. An interval outside the proposal's range
    (or of zero width at a proposal edge) overlaps nothing and is bounded by 0.

    Args: edges [..., S+1], proposal_edges [..., P+1], proposal_weights [..., P]; the same leading shape.
    """
    cumulative = torch.cat([torch.zeros_like(proposal_weights[..., :1]), torch.cumsum(proposal_weights, -1)], -1)
    first = torch.searchsorted(proposal_edges[..., 1:].contiguous(), edges[..., :-1].contiguous(), right=True)
    stop = torch.searchsorted(proposal_edges[..., :-1].contiguous(), edges[..., 1:].contiguous(), right=False)
    stop = torch.maximum(stop, first)  # no overlap: an empty run of intervals
    return cumulative.gather(-1, stop) - cumulative.gather(-1, first)


def interlevel_loss(edges: Tensor, weights: Tensor, proposal_edges: Tensor, proposal_weights: Tensor) -> Tensor:
    """mip-NeRF 360's proposal loss (eq. 13) per ray: sum_i max(0, w_i - bound_i)^2 / w_i: [...].

    Zero where the proposal's histogram bounds the NeRF's weights ``weights`` from above in every interval;
    positive where it misses some of their mass. The NeRF's side is detached: the loss trains the proposal
    only. An interval of zero weight contributes 0 (max(0, 0 - bound) = 0), so the division is taken only
    where w_i > 0 (guarded by selection, no epsilon).

    Args: edges [..., S+1], weights [..., S] (the NeRF's); proposal_edges [..., P+1], proposal_weights [..., P].

    Example: a NeRF weight 0.5 in [0, 1], a proposal weight 0.2 over [0, 2]: (0.5 - 0.2)^2 / 0.5 = 0.18.
    >>> interlevel_loss(torch.tensor([0.0, 1]), torch.tensor([0.5]), torch.tensor([0.0, 2]), torch.tensor([0.2]))
    tensor(0.1800)
    """
    edges, weights = edges.detach(), weights.detach()
    excess = torch.relu(weights - outer_bound(edges, proposal_edges, proposal_weights))
    positive = weights > 0
    return torch.where(positive, excess.square() / torch.where(positive, weights, 1), 0).sum(-1)


def distortion_loss(edges: Tensor, weights: Tensor) -> Tensor:
    """mip-NeRF 360's distortion loss (eq. 15) per ray, for edges normalized to [0, 1] along the ray: [...].

    L = sum_{i,j} w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 (s_{i+1} - s_i), m_i the interval midpoints: small
    when the weights gather in one short stretch of the ray (a surface), large when spread (floaters, fog).
    The double sum in O(S): for sorted midpoints it is 2 sum_i w_i (m_i W_i - M_i), with W_i = sum_{j<i} w_j
    and M_i = sum_{j<i} w_j m_j (``tests/nerf/test_proposal.py`` checks it against the double sum).

    Args: edges [..., S+1] sorted, weights [..., S].
    """
    midpoints = (edges[..., 1:] + edges[..., :-1]) / 2
    before = torch.cumsum(weights, -1) - weights  # W_i
    moment_before = torch.cumsum(weights * midpoints, -1) - weights * midpoints  # M_i
    between = 2 * (weights * (midpoints * before - moment_before)).sum(-1)
    within = (weights.square() * (edges[..., 1:] - edges[..., :-1])).sum(-1) / 3
    return between + within


class ProposalSampler(Sampler):
    """The proposal networks, their settings and their sampling (``nerfexp.nerf.samplers``): round k evaluates
    network k at ``n_samples[k]`` samples (stratified for the first round, else drawn from the previous round's
    histogram, dilated by one interval); the field (named "coarse", as without hierarchy) evaluates ``n_final``
    samples drawn from the last round's, and in training its output holds the interlevel (and distortion) losses
    under ``regularizers``. The proposals are queried through the renderer's occupancy grid too: the grid learns
    the field's density, and a proposal need not place samples where the field is empty.

    Args:
        network: builds a density-only network (``nerfexp.nerf.fields.DensityField``), once per round.
        n_samples: samples per round, one entry per proposal network (mip-NeRF 360: 64, 64).
        n_final: samples the NeRF evaluates (mip-NeRF 360: 32).
        interlevel_weight: the interlevel loss's weight (mip-NeRF 360: 1); it alone trains the proposals.
        distortion_weight: the distortion loss's weight on the NeRF's weights (mip-NeRF 360: 0.01,
            nerfacto: 0.002); 0: off.
    """

    DOMAINS = {
        # the networks' own: nerfexp.nerf.fields.DensityField.DOMAINS
        "n_samples": ("a non-empty list of sample counts, each a whole number >= 1",
                      lambda v: isinstance(v, list) and v != [] and all(COUNT[1](n) for n in v)),
        "n_final": COUNT,
        "interlevel_weight": real(0, LOSS_WEIGHT_LIMIT, above=True),  # it alone trains the proposal networks
        "distortion_weight": LOSS_WEIGHT,
    }

    def __init__(self, network: Callable[[], nn.Module], n_samples: Sequence[int], n_final: int,
                 interlevel_weight: float = 1.0, distortion_weight: float = 0.0):
        super().__init__()
        if len(n_samples) == 0:
            raise ValueError("proposal.n_samples: expected one sample count per round, at least one round")
        self.networks = nn.ModuleList(network() for _ in n_samples)
        self.n_samples = list(n_samples)
        self.n_final = n_final
        self.interlevel_weight = interlevel_weight
        self.distortion_weight = distortion_weight

    @staticmethod
    def SAMPLES_PER_RAY(config: Mapping) -> tuple[int, tuple[str, ...]]:
        return sum(config["n_samples"]) + config["n_final"], ("n_samples", "n_final")

    @property
    def samples_per_ray(self) -> int:
        return self.SAMPLES_PER_RAY(vars(self))[0]

    @property
    def colour_samples_per_ray(self) -> int:
        return self.n_final  # the proposal networks have no colour

    def render(self, rays: Rays, steps: Steps, deterministic: bool) -> dict[str, dict[str, Tensor]]:
        """{"coarse": the field's output}; in training (with gradients enabled) the output's ``regularizers``
        hold the proposal losses."""
        counts = [*self.n_samples, self.n_final]  # samples of each round, then the field's
        t = first_samples(rays, counts[0], deterministic)
        histograms, evaluated = [], 0
        for net, n_next in zip(self.networks, counts[1:]):
            weights, evaluated_here = steps.density_weights(net, rays, t)
            histograms.append((resampling_bins(t, rays.near, rays.far), weights))
            evaluated = evaluated + evaluated_here
            t = resample(rays, t, weights, n_next, deterministic)
        out = steps.composited("coarse", rays, t)
        out["evaluated"] = out["evaluated"] + evaluated
        if torch.is_grad_enabled():
            edges = torch.cat([t, rays.far[:, None]], -1)  # the field's intervals [t_i, t_{i+1}], the last to far
            losses = self.losses(edges, out["weights"], histograms, rays)
            out["regularizers"] = {**out.get("regularizers", {}), **losses}
        return {"coarse": out}

    def losses(self, edges: Tensor, weights: Tensor, histograms: list[tuple[Tensor, Tensor]],
               rays: Rays) -> dict[str, Tensor]:
        """The weighted regularizers of a batch, means over its rays: ``interlevel`` (summed over rounds) and,
        with a positive ``distortion_weight``, ``distortion``.

        Args: the NeRF's ``edges`` [B, S+1] and ``weights`` [B, S]; ``histograms`` each round's (edges
        [B, P+1], weights [B, P]); the ``rays``, whose near and far normalize the distortion's distances (or,
        with a ``split``, the fraction of ``disparity_spaced``: mip-NeRF 360 measures it so).
        """
        interlevel = sum(interlevel_loss(edges, weights, e, w).mean() for e, w in histograms)
        losses = {"interlevel": self.interlevel_weight * interlevel}
        if self.distortion_weight > 0:
            near, far = rays.near, rays.far
            normalized = ((edges - near[:, None]) / (far - near)[:, None] if rays.split is None
                          else disparity_fraction(edges, near, rays.split, far))
            losses["distortion"] = self.distortion_weight * distortion_loss(normalized, weights).mean()
        return losses
