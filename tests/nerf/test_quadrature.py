import math

import pytest
import torch

from nerfexp.nerf.quadrature import composite, render_weights


@pytest.mark.parametrize("sigma", [0.0, 1e-6, 0.3, 2.0, 50.0])
def test_constant_density_segment_opacity_is_closed_form(sigma, device):
    # A segment [0, L] of constant density, cut into S intervals: the weights sum to 1 - exp(-sigma L)
    # exactly, whatever S, since the quadrature of a constant is exact.
    length, S = 1.7, 13
    edges = torch.linspace(0, length, S + 1, dtype=torch.float64)
    sigmas = torch.full((S,), sigma, dtype=torch.float64)
    weights, transmittance = render_weights(sigmas.to(device), edges[:-1].to(device), edges[1:].to(device))
    assert math.isclose(weights.sum().item(), -math.expm1(-sigma * length), rel_tol=1e-12, abs_tol=1e-300)
    torch.testing.assert_close(transmittance.cpu(), torch.exp(-sigma * edges[:-1]), rtol=1e-12, atol=0)


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


def test_weights_match_float64_reference_and_gradients_are_finite(device):
    torch.manual_seed(0)
    sigmas = (torch.rand(8, 32) * 20).to(device).requires_grad_()
    t = torch.sort(torch.rand(8, 33) * 4 + 2, -1).values.to(device)
    weights, _ = render_weights(sigmas, t[:, :-1], t[:, 1:])
    weights, t = weights.cpu(), t.cpu()
    # Reference: the textbook product form, in float64 on the CPU.
    s, d = sigmas.detach().cpu().double(), (t[:, 1:] - t[:, :-1]).double()
    alpha = 1 - torch.exp(-s * d)
    trans = torch.cumprod(torch.cat([torch.ones(8, 1, dtype=torch.float64), 1 - alpha[:, :-1]], 1), 1)
    torch.testing.assert_close(weights.double(), trans * alpha, rtol=1e-5, atol=1e-6)
    weights.sum().backward()
    assert torch.isfinite(sigmas.grad).all()


def test_composite_colour_depth_opacity(device):
    # Half the light stops at t in [1, 2] (colour red), the rest reaches a white background.
    weights = torch.tensor([[0.0, 0.5, 0.0]], device=device)
    rgbs = torch.tensor([[[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]], device=device)
    mids = torch.tensor([[0.5, 1.5, 2.5]], device=device)
    out = composite(weights, rgbs, mids, torch.ones(3, device=device), far=6.0)
    torch.testing.assert_close(out["rgb"].cpu(), torch.tensor([[1.0, 0.5, 0.5]]))
    torch.testing.assert_close(out["opacity"].cpu(), torch.tensor([0.5]))
    torch.testing.assert_close(out["depth"].cpu(), torch.tensor([1.5]))


def test_composite_empty_ray_is_background_at_far_depth():
    out = composite(torch.zeros(2, 4), torch.rand(2, 4, 3), torch.rand(2, 4), torch.zeros(3), far=6.0)
    torch.testing.assert_close(out["rgb"], torch.zeros(2, 3))
    torch.testing.assert_close(out["depth"], torch.full((2,), 6.0))


# ---- stiff and extreme inputs, against a float64 product-form reference ---------------------------------


def reference_weights(sigmas: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor) -> torch.Tensor:
    """The textbook product form in float64, written independently: w_i = prod_{j<i} (1 - a_j) a_i,
    a_i = 1 - exp(-sigma_i delta_i), with the physical conventions for the edge cases written out:
    an interval of zero density or zero length absorbs nothing; an infinite one of positive density
    absorbs everything."""
    s = sigmas.double().flatten().tolist()
    starts, ends = t_starts.double().flatten().tolist(), t_ends.double().flatten().tolist()
    weights, transmittance = [], 1.0
    for sigma, a, b in zip(s, starts, ends):
        delta = b - a
        if sigma == 0 or delta == 0:
            alpha = 0.0
        elif math.isinf(sigma) or math.isinf(delta):
            alpha = 1.0
        else:
            alpha = -math.expm1(-sigma * delta)
        weights.append(transmittance * alpha)
        transmittance *= 1 - alpha
    return torch.tensor(weights, dtype=torch.float64).reshape(sigmas.shape)


SIGMAS = [0.0, 1e-30, 1e-6, 1.0, 1e3, 1e6, 1e12, math.inf]
DELTAS = [0.0, 1e-6, 1e-2, 1.0, 1e10, math.inf]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("delta", DELTAS)
@pytest.mark.parametrize("sigma", SIGMAS)
def test_one_extreme_interval_between_ordinary_ones(sigma, delta, dtype):
    # intervals [2, 2.5], [2.5, 2.5 + delta], then [.., +0.5]: the extreme one in the middle, or last
    # where it is infinite (the background interval)
    n = 2 if math.isinf(delta) else 3
    sigmas = torch.tensor([0.7, sigma, 1.3][:n], dtype=dtype, requires_grad=True)
    t0, t1 = 2.0, 2.5
    starts = torch.tensor([t0, t1, t1 + delta][:n], dtype=dtype)
    ends = torch.tensor([t1, t1 + delta, t1 + delta + 0.5][:n], dtype=dtype)
    weights, transmittance = render_weights(sigmas, starts, ends)
    expected = reference_weights(sigmas.detach(), starts, ends)
    assert torch.isfinite(weights).all() and torch.isfinite(transmittance).all()
    torch.testing.assert_close(weights.double(), expected, rtol=1e-5, atol=1e-7)
    assert (weights >= 0).all() and weights.sum() <= 1 + 4 * torch.finfo(dtype).eps
    (weights * torch.tensor([0.3, -0.8, 0.5][:n], dtype=dtype)).sum().backward()
    assert torch.isfinite(sigmas.grad).all()


def test_opaque_thin_shell_closed_form():
    # sigma = 1e6 over a width of 1e-6: optical depth 1, so the shell absorbs 1 - 1/e of the light,
    # whether it sits at t = 1e-3 or t = 4 (float64), and whatever the (empty) intervals around it.
    for t_shell in (1e-3, 4.0):
        t = torch.tensor([0.0, t_shell, t_shell + 1e-6, 6.0], dtype=torch.float64)
        sigmas = torch.tensor([0.0, 1e6, 0.0], dtype=torch.float64)
        weights, _ = render_weights(sigmas, t[:-1], t[1:])
        # (the width 1e-6 is itself rounded at t = 4: compare with the width that was represented)
        width = (t[2] - t[1]).item()
        assert math.isclose(weights[1].item(), -math.expm1(-1e6 * width), rel_tol=1e-14)
        assert math.isclose(width * 1e6, 1.0, rel_tol=1e-9)


def test_background_interval_of_infinite_length():
    # The last interval reaching to infinity: empty (sigma = 0) shows the background, any positive
    # density absorbs all light that is left; never 0 * inf = nan.
    t_starts = torch.tensor([[2.0, 3.0], [2.0, 3.0]])
    t_ends = torch.tensor([[3.0, math.inf], [3.0, math.inf]])
    sigmas = torch.tensor([[0.5, 0.0], [0.5, 1e-20]], requires_grad=True)
    weights, _ = render_weights(sigmas, t_starts, t_ends)
    opacity_front = -math.expm1(-0.5)
    torch.testing.assert_close(weights, torch.tensor([[opacity_front, 0.0], [opacity_front, 1 - opacity_front]]))
    weights.sum().backward()
    assert torch.isfinite(sigmas.grad).all()


def test_ray_starting_inside_a_solid():
    # A ray starting at t = 0 inside a medium of density s filling [0, 1]: opacity 1 - exp(-s) for any
    # sampling; for s -> inf all light stops at the start: depth 0 and disparity inf (its true value),
    # never nan.
    t = torch.linspace(0, 1, 65, dtype=torch.float64)
    for s, depth in ((2.0, None), (1e12, 0.0)):
        weights, _ = render_weights(torch.full((64,), s, dtype=torch.float64), t[:-1], t[1:])
        out = composite(weights, torch.rand(64, 3, dtype=torch.float64), t[:-1], torch.ones(3, dtype=torch.float64),
                        far=6.0)
        assert math.isclose(out["opacity"].item(), -math.expm1(-s), rel_tol=1e-12)
        if depth is not None:
            assert out["depth"].item() == depth and out["disparity"].item() == math.inf


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_rays_of_length_zero_and_near_equal_to_far(dtype):
    # near == far: every interval has zero length, so nothing is absorbed, whatever the density.
    from nerfexp.nerf.sampling import intervals, stratified_samples

    near = torch.full((3,), 4.0, dtype=dtype)
    t = stratified_samples(near, near.clone(), 8, deterministic=False)
    starts, ends = intervals(t, near)
    sigmas = torch.tensor([0.0, 1.0, math.inf], dtype=dtype)[:, None].expand(3, 8).clone().requires_grad_()
    weights, transmittance = render_weights(sigmas, starts, ends)
    out = composite(weights, torch.rand(3, 8, 3, dtype=dtype), t, torch.ones(3, dtype=dtype), far=4.0)
    assert torch.equal(weights, torch.zeros_like(weights)) and torch.equal(transmittance, torch.ones_like(t))
    assert torch.equal(out["rgb"], torch.ones(3, 3, dtype=dtype))
    assert torch.equal(out["depth"], torch.full((3,), 4.0, dtype=dtype))
    out["rgb"].sum().backward()
    assert torch.isfinite(sigmas.grad).all()


def test_disparity_of_an_empty_ray_is_one_over_far():
    out = composite(torch.zeros(1, 4), torch.rand(1, 4, 3), torch.rand(1, 4), torch.ones(3), far=6.0)
    assert out["disparity"].item() == pytest.approx(1 / 6)


def test_depth_of_a_barely_absorbing_ray_is_its_true_depth():
    # Opacity 1e-30 (a denormal-free float64 value): the guarded division keeps the true depth 3.0; an
    # additive epsilon (depth_sum / (opacity + 1e-10)) would report ~0.
    weights = torch.tensor([[0.0, 1e-30, 0.0]], dtype=torch.float64)
    out = composite(weights, torch.zeros(1, 3, 3, dtype=torch.float64), torch.tensor([[2.0, 3.0, 4.0]],
                    dtype=torch.float64), torch.ones(3, dtype=torch.float64), far=6.0)
    assert out["depth"].item() == 3.0


# ---- properties over the whole range a training run can produce (hypothesis) ---------------------------

from hypothesis import example, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

sigma_values = st.one_of(st.just(0.0), st.floats(0.0, 1e12, allow_subnormal=False),
                         st.floats(1e-8, 1e3).map(float))
delta_values = st.one_of(st.just(0.0), st.floats(0.0, 1e10, allow_subnormal=False), st.floats(1e-6, 1.0))


@st.composite
def rays(draw):
    """One ray of S intervals: densities, and interval edges from a start in [0, 10] and lengths
    from 0 to 1e10; the last interval may reach to infinity (the background)."""
    S = draw(st.integers(1, 24))
    sigmas = draw(st.lists(sigma_values, min_size=S, max_size=S))
    deltas = draw(st.lists(delta_values, min_size=S, max_size=S))
    if draw(st.booleans()):
        deltas[-1] = math.inf
    start = draw(st.floats(0.0, 10.0))
    edges = [start]
    for d in deltas:
        edges.append(edges[-1] + d)
    return sigmas, edges


@settings(max_examples=300, deadline=None)
@given(rays())
def test_render_weights_properties(ray):
    sigmas, edges = ray
    t64 = torch.tensor(edges, dtype=torch.float64)
    s32 = torch.tensor(sigmas, dtype=torch.float32, requires_grad=True)
    t32 = t64.float()  # float32 edges: the reference below is evaluated on the same rounded values
    weights, transmittance = render_weights(s32, t32[:-1], t32[1:])
    assert torch.isfinite(weights).all() and torch.isfinite(transmittance).all()
    assert (weights >= 0).all() and (transmittance >= 0).all() and (transmittance <= 1).all()
    assert weights.sum().item() <= 1 + len(sigmas) * torch.finfo(torch.float32).eps
    # float32 against float64 on the same inputs: the optical depths round by a few ulps (relative),
    # which moves each exp(-tau) by at most a few 1e-7 (|d exp(-tau)/d tau| * tau = tau e^-tau <= 1/e)
    expected = reference_weights(s32.detach(), t32[:-1], t32[1:])
    torch.testing.assert_close(weights.double(), expected, rtol=0, atol=len(sigmas) * 4e-7)
    weights64, _ = render_weights(s32.detach().double(), t32[:-1].double(), t32[1:].double())
    torch.testing.assert_close(weights64, expected, rtol=1e-9, atol=1e-12)
    colours = torch.linspace(-1, 1, len(sigmas))
    (weights * colours).sum().backward()
    assert torch.isfinite(s32.grad).all()


@settings(max_examples=200, deadline=None)
@given(rays(), st.floats(0.0, 1.0))
@example(([1.401298464324817e-45, 0.0, 0.0, 0.0], [1.5, 2.5, 2.5, 2.5, 2.5]), 0.0)  # found: one denormal weight
def test_composite_properties(ray, background):
    sigmas, edges = ray
    t = torch.tensor(edges, dtype=torch.float32)
    weights, _ = render_weights(torch.tensor(sigmas), t[:-1], t[1:])
    rgbs = torch.rand(len(sigmas), 3)
    far = t[-1].item() if math.isfinite(edges[-1]) else 1e10
    out = composite(weights, rgbs, t[:-1], torch.full((3,), background), far=far)
    assert all(torch.isfinite(out[k]).all() for k in ("rgb", "opacity", "depth"))
    eps = len(sigmas) * torch.finfo(torch.float32).eps
    assert ((out["rgb"] >= -eps) & (out["rgb"] <= 1 + eps)).all()
    if out["opacity"] > 0:  # the expected depth lies between the first and the last absorbing sample
        absorbing = t[:-1][weights > 0]
        assert absorbing.min() * (1 - eps) <= out["depth"] <= absorbing.max() * (1 + eps)
    else:
        assert out["depth"].item() == far
