import math

import pytest
import torch

from nerfexp.rendering import composite, render_weights


@pytest.mark.parametrize("sigma", [0.0, 1e-6, 0.3, 2.0, 50.0])
def test_constant_density_segment_opacity_is_closed_form(sigma):
    # A segment [0, L] of constant density, cut into S intervals: the weights sum to 1 - exp(-sigma L)
    # exactly, whatever S, since the quadrature of a constant is exact.
    length, S = 1.7, 13
    edges = torch.linspace(0, length, S + 1, dtype=torch.float64)
    sigmas = torch.full((S,), sigma, dtype=torch.float64)
    weights, transmittance = render_weights(sigmas, edges[:-1], edges[1:])
    assert math.isclose(weights.sum().item(), -math.expm1(-sigma * length), rel_tol=1e-12, abs_tol=1e-300)
    torch.testing.assert_close(transmittance, torch.exp(-sigma * edges[:-1]), rtol=1e-12, atol=0)


def test_float32_small_optical_depth_keeps_relative_precision():
    # 1 - exp(-tau) in float32 loses everything at tau = 1e-9; -expm1(-tau) does not.
    sigmas = torch.tensor([1e-9], dtype=torch.float32)
    weights, _ = render_weights(sigmas, torch.tensor([0.0]), torch.tensor([1.0]))
    assert math.isclose(weights.item(), 1e-9, rel_tol=1e-6)


def test_opaque_interval_blocks_everything_behind_it():
    sigmas = torch.tensor([0.0, math.inf, 1.0, 5.0])
    t = torch.tensor([0.0, 1.0, 2.0, 3.0, 4.0])
    weights, transmittance = render_weights(sigmas, t[:-1], t[1:])
    torch.testing.assert_close(weights, torch.tensor([0.0, 1.0, 0.0, 0.0]))
    torch.testing.assert_close(transmittance, torch.tensor([1.0, 1.0, 0.0, 0.0]))


def test_weights_match_float64_reference_and_gradients_are_finite():
    torch.manual_seed(0)
    sigmas = (torch.rand(8, 32) * 20).requires_grad_()
    t = torch.sort(torch.rand(8, 33) * 4 + 2, -1).values
    weights, _ = render_weights(sigmas, t[:, :-1], t[:, 1:])
    # Reference: the textbook product form, in float64.
    s, d = sigmas.detach().double(), (t[:, 1:] - t[:, :-1]).double()
    alpha = 1 - torch.exp(-s * d)
    trans = torch.cumprod(torch.cat([torch.ones(8, 1, dtype=torch.float64), 1 - alpha[:, :-1]], 1), 1)
    torch.testing.assert_close(weights.double(), trans * alpha, rtol=1e-5, atol=1e-6)
    weights.sum().backward()
    assert torch.isfinite(sigmas.grad).all()


def test_composite_colour_depth_opacity():
    # Half the light stops at t in [1, 2] (colour red), the rest reaches a white background.
    weights = torch.tensor([[0.0, 0.5, 0.0]])
    rgbs = torch.tensor([[[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]])
    mids = torch.tensor([[0.5, 1.5, 2.5]])
    out = composite(weights, rgbs, mids, torch.ones(3), far=6.0)
    torch.testing.assert_close(out["rgb"], torch.tensor([[1.0, 0.5, 0.5]]))
    torch.testing.assert_close(out["opacity"], torch.tensor([0.5]))
    torch.testing.assert_close(out["depth"], torch.tensor([1.5]))


def test_composite_empty_ray_is_background_at_far_depth():
    out = composite(torch.zeros(2, 4), torch.rand(2, 4, 3), torch.rand(2, 4), torch.zeros(3), far=6.0)
    torch.testing.assert_close(out["rgb"], torch.zeros(2, 3))
    torch.testing.assert_close(out["depth"], torch.full((2,), 6.0))
