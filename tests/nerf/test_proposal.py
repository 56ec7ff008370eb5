"""Proposal sampling (mip-NeRF 360): the interlevel loss's bound against a brute-force overlap sum and
hand-worked values, the distortion loss against its double sum, and the renderer's rounds resampling a
known density."""

import functools
import math

import pytest
import torch

from nerfexp.nerf.encodings import IdentityEncoding
from nerfexp.nerf.fields import DensityField, FieldOutputs
from nerfexp.nerf.hierarchy import HierarchyChoice
from nerfexp.nerf.proposal import ProposalSampler, distortion_loss, interlevel_loss, outer_bound
from nerfexp.nerf.samplers import Rays
from nerfexp.nerf.sampling import dilate_weights, resampling_bins, sample_pdf, stratified_samples
from nerfexp.nerf.volume_renderer import VolumeRenderer
from tests.analytic import rays_down_z, slab


def random_histogram(generator, n, low=0.0, high=1.0):
    """Sorted edges [n + 1] spanning [low, high] and weights [n] summing to at most 1 (some exactly 0)."""
    inner = torch.sort(torch.rand(n - 1, generator=generator, dtype=torch.float64)).values * (high - low) + low
    edges = torch.cat([torch.tensor([low], dtype=torch.float64), inner, torch.tensor([high], dtype=torch.float64)])
    weights = torch.rand(n, generator=generator, dtype=torch.float64) * (torch.rand(n, generator=generator) > 0.3)
    return edges, weights / n


def brute_force_bound(edges, proposal_edges, proposal_weights):
    """sum of w_hat_j over every j with [e_hat_j, e_hat_{j+1}] overlapping [e_i, e_{i+1}] (open intervals)."""
    return torch.tensor([sum(float(w) for w, lo, hi in zip(proposal_weights, proposal_edges[:-1], proposal_edges[1:])
                             if lo < b and hi > a) for a, b in zip(edges[:-1], edges[1:])], dtype=torch.float64)


@pytest.mark.parametrize("seed", range(5))
def test_the_outer_bound_is_the_sum_over_overlapping_proposal_intervals(seed):
    generator = torch.Generator().manual_seed(seed)
    edges, _ = random_histogram(generator, 12, 0.1, 0.9)  # inside the proposal's range, and crossing its edges
    proposal_edges, proposal_weights = random_histogram(generator, 7)
    expected = brute_force_bound(edges, proposal_edges, proposal_weights)
    torch.testing.assert_close(outer_bound(edges, proposal_edges, proposal_weights), expected, rtol=0, atol=1e-15)
    # batched: [R, ...] rays give each ray's bound
    stacked = outer_bound(edges.expand(3, -1), proposal_edges.expand(3, -1), proposal_weights.expand(3, -1))
    torch.testing.assert_close(stacked, expected.expand(3, -1), rtol=0, atol=1e-15)


def test_intervals_sharing_an_edge_with_the_proposal_overlap_only_the_intervals_they_cross():
    # proposal [0, 1] -> 0.25, [1, 2] -> 0.5; the NeRF's [0, 1] lies in the first only, [0.5, 1.5] crosses both,
    # [1, 1] (zero width at the shared edge) overlaps neither, [2, 3] lies outside the proposal's range
    proposal_edges, proposal_weights = torch.tensor([0.0, 1, 2]), torch.tensor([0.25, 0.5])
    bound = outer_bound(torch.tensor([[0.0, 1], [0.5, 1.5], [1, 1], [2, 3]]), proposal_edges.expand(4, -1),
                        proposal_weights.expand(4, -1))
    assert bound.squeeze(-1).tolist() == [0.25, 0.75, 0.0, 0.0]


def test_the_interlevel_loss_is_zero_where_the_proposal_bounds_the_weights_and_positive_where_not():
    edges = torch.tensor([0.0, 1, 2, 3, 4])
    weights = torch.tensor([0.0, 0.5, 0.3, 0.0])
    # a proposal of two wide intervals holding at least the mass the NeRF puts in each: bounded, loss 0
    assert interlevel_loss(edges, weights, torch.tensor([0.0, 2, 4]), torch.tensor([0.5, 0.3])) == 0
    # the NeRF's own histogram bounds itself
    assert interlevel_loss(edges, weights, edges, weights) == 0
    # hand-worked: the proposal puts 0.2 over [0, 2] and 0.1 over [2, 4]: the NeRF's 0.5 in [1, 2] exceeds
    # its bound 0.2 by 0.3 -> 0.09 / 0.5 = 0.18; its 0.3 in [2, 3] exceeds 0.1 by 0.2 -> 0.04 / 0.3
    proposal_weights = torch.tensor([0.2, 0.1], requires_grad=True)
    loss = interlevel_loss(edges, weights.requires_grad_(), torch.tensor([0.0, 2, 4]), proposal_weights)
    assert loss.item() == pytest.approx(0.18 + 0.04 / 0.3, rel=1e-6)
    loss.backward()
    # it trains the proposal (raising its weights lowers the loss) and leaves the NeRF's weights alone
    assert (proposal_weights.grad < 0).all() and weights.grad is None


def test_the_interlevel_loss_of_zero_weights_is_zero_with_finite_gradients():
    proposal_weights = torch.zeros(3, requires_grad=True)
    loss = interlevel_loss(torch.tensor([0.0, 1, 2]), torch.zeros(2), torch.tensor([0.0, 1, 2, 3]), proposal_weights)
    loss.backward()
    assert loss == 0 and torch.isfinite(proposal_weights.grad).all()


@pytest.mark.parametrize("seed", range(5))
def test_the_distortion_loss_equals_its_double_sum(seed):
    generator = torch.Generator().manual_seed(seed)
    edges, weights = random_histogram(generator, 9)
    midpoints = (edges[1:] + edges[:-1]) / 2
    double_sum = sum(weights[i] * weights[j] * abs(midpoints[i] - midpoints[j]) for i in range(9) for j in range(9))
    expected = double_sum + sum(weights[i] ** 2 * (edges[i + 1] - edges[i]) for i in range(9)) / 3
    torch.testing.assert_close(distortion_loss(edges, weights), expected, rtol=1e-12, atol=0)


def test_the_distortion_loss_prefers_one_short_surface_to_spread_weights():
    edges = torch.linspace(0, 1, 11)
    surface = torch.zeros(10).index_fill(0, torch.tensor([4]), 0.9)  # 0.9 in one interval of 0.1
    # one interval alone: no pairs, 0.9^2 * 0.1 / 3
    assert distortion_loss(edges, surface).item() == pytest.approx(0.81 * 0.1 / 3)
    assert distortion_loss(edges, torch.full((10,), 0.09)) > distortion_loss(edges, surface)


def proposal_renderer(n_samples, n_final, proposal_field=slab):
    """Slab field and proposal networks (the exact density), rays from z = 4 down to a slab at |z| < 0.5."""
    sampler = functools.partial(ProposalSampler, proposal_field, n_samples=n_samples, n_final=n_final)
    return VolumeRenderer(slab, sampler, near=2.0, far=6.0)


def test_the_field_evaluates_only_samples_drawn_from_the_last_proposal_histogram():
    # The proposals see the exact slab: the field's samples must be the deterministic quantiles of the dilated
    # histogram of the last round's weights, computed here from that round's samples.
    renderer = proposal_renderer([8, 16], 24)
    origins, directions = rays_down_z(1)
    out = renderer(origins, directions, deterministic=True)
    assert set(out) == {"coarse"} and renderer.fine is None
    assert out["coarse"]["weights"].shape == (1, 24) and renderer.samples_per_ray == 8 + 16 + 24
    near, far = torch.full((1,), 2.0, dtype=torch.float64), torch.full((1,), 6.0, dtype=torch.float64)
    t = stratified_samples(near, far, 8, deterministic=True)
    for n_next in (16, 24):
        weights, _ = renderer.density_weights(renderer.sampler.networks[0], Rays(origins, directions, directions,
                                                                                 near, far), t)
        t = sample_pdf(resampling_bins(t, near, far), dilate_weights(weights), n_next, deterministic=True)
    torch.testing.assert_close(out["coarse"]["t_starts"], t, rtol=0, atol=0)
    # the slab lies at t in (3.5, 4.5): every sample the field evaluates is within a first-round spacing of it
    assert ((t > 3.5 - 0.5) & (t < 4.5 + 0.5)).all()


def test_proposal_rendering_of_a_slab_converges_to_the_closed_form():
    # As the hierarchy's test: opacity 1 - exp(-3 * 1) through the slab; 8 uniform samples miss it by O(0.1),
    # the field's samples concentrated by the proposals resolve it.
    exact = -math.expm1(-3.0)
    errors = [abs(proposal_renderer([8], n)(*rays_down_z(1), deterministic=True)["coarse"]["opacity"].item() - exact)
              for n in (8, 128)]
    assert errors[1] < 5e-3 and errors[1] < errors[0]


def test_the_proposal_networks_train_on_the_interlevel_loss_alone():
    def network():
        return DensityField(IdentityEncoding(), depth=2, width=16, skips=(), density_activation="softplus")

    renderer = proposal_renderer([8, 8], 8, proposal_field=network)
    renderer.coarse = DensityFieldWithColour()
    out = renderer(*(t.float() for t in rays_down_z(4)), deterministic=False)["coarse"]
    assert set(out["regularizers"]) == {"interlevel"}  # the distortion loss is off by default
    out["rgb"].sum().backward()  # the colour: no gradient reaches the proposals
    assert all(p.grad is None for p in renderer.sampler.parameters())
    out["regularizers"]["interlevel"].backward()
    grads = [p.grad for p in renderer.sampler.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads) and any(g.abs().sum() > 0 for g in grads)
    with torch.no_grad():  # rendering for evaluation computes no losses
        assert "regularizers" not in renderer(*(t.float() for t in rays_down_z(4)), deterministic=True)["coarse"]


class DensityFieldWithColour(torch.nn.Module):
    """The slab as a trainable field: density 3 where |z| < 0.5 times a learnt scale, grey."""

    def __init__(self):
        super().__init__()
        self.scale = torch.nn.Parameter(torch.ones(()))

    def forward(self, positions, directions):
        sigma = self.scale * 3.0 * (positions[..., 2].abs() < 0.5)
        return FieldOutputs(rgb=torch.full((*sigma.shape, 3), 0.5) * self.scale, sigma=sigma)


def test_the_distortion_loss_is_added_with_its_weight():
    sampler = functools.partial(ProposalSampler, slab, n_samples=[8], n_final=16, distortion_weight=0.01)
    renderer = VolumeRenderer(slab, sampler, near=2.0, far=6.0)
    out = renderer(*rays_down_z(2), deterministic=True)["coarse"]
    edges = (torch.cat([out["t_starts"], torch.full((2, 1), 6.0, dtype=torch.float64)], -1) - 2) / 4
    expected = 0.01 * distortion_loss(edges, out["weights"]).mean()
    torch.testing.assert_close(out["regularizers"]["distortion"], expected)


def test_a_proposal_renderer_needs_its_sampler_and_hierarchical_takes_three_values():
    with pytest.raises(ValueError, match="hierarchical=proposal needs the proposal networks"):
        VolumeRenderer(slab, HierarchyChoice("proposal", 8, 8, 8), near=2.0, far=6.0)
    with pytest.raises(ValueError, match="hierarchical: expected true, false or proposal, got 'coarse'"):
        VolumeRenderer(slab, HierarchyChoice("coarse", 8, 8, 8), near=2.0, far=6.0)
