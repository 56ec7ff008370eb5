"""The compositing kernel (src/nerfexp/kernels/composite.cpp, through ``nerfexp.nerf.compositing.rendered``) against
independent truth and the torch path it replaces (``quadrature.render_weights`` then ``composite``): the closed
form of a constant density, float64 gradients of every output against the torch path's and finite differences,
rays that absorb nothing, opaque and infinite intervals, zero-width ones, empty batches, NaN densities; the torch
path where the kernel does not compute what is asked (gradients of the intervals, other devices and dtypes); a
wrong call as one line; and the renderer's pixels and gradients alike on both paths."""

import functools
import math

import pytest
import torch

from nerfexp import kernels
from nerfexp.nerf import compositing
from nerfexp.nerf.compositing import fused_kernel, rendered
from nerfexp.nerf.quadrature import composite, render_weights

FUSED = kernels.kernel(compositing.KERNEL)
needs_kernel = pytest.mark.skipif(FUSED is None, reason="the composite kernel was not built (no C++ compiler)")
OUTPUTS = ("rgb", "depth", "disparity", "opacity")


def rays(B: int, S: int, dtype=torch.float64, seed: int = 0) -> dict[str, torch.Tensor]:
    """Random rays' samples: densities with exact zeros, sorted t in [2, 6], contiguous intervals ending at
    6 (the last one, on every other ray, at infinity), colours in [0, 1]."""
    g = torch.Generator().manual_seed(seed)
    sigmas = torch.rand(B, S, generator=g, dtype=dtype) * 3
    sigmas[torch.rand(B, S, generator=g) < 0.2] = 0
    t = (2 + 4 * torch.rand(B, S, generator=g, dtype=dtype)).sort(-1).values
    ends = torch.cat([t[:, 1:], torch.full((B, 1), 6.0, dtype=dtype)], -1)
    ends[::2, -1] = math.inf
    return {"sigmas": sigmas, "rgbs": torch.rand(B, S, 3, generator=g, dtype=dtype), "starts": t.clone(),
            "ends": ends, "t": t, "background": torch.tensor([1.0, 0.5, 0.0], dtype=dtype)}


def torch_path(sigmas, rgbs, starts, ends, t, background, far):
    weights, _ = render_weights(sigmas, starts, ends)
    return weights, composite(weights, rgbs, t, background, far)


def outputs_and_grads(render, inputs: dict, far: float = 6.0, seed: int = 1):
    """``render``'s weights and composite, and the gradients of the densities and colours under a random
    combination of every output (the weights' too)."""
    leaves = {k: v.clone().requires_grad_(k in ("sigmas", "rgbs")) for k, v in inputs.items()}
    weights, out = render(**leaves, far=far)
    g = torch.Generator().manual_seed(seed)
    probe = lambda x: torch.randn(x.shape, generator=g, dtype=x.dtype)  # noqa: E731
    finite = lambda x: torch.where(torch.isfinite(x), x, 0)  # noqa: E731  (disparity can be inf at depth 0)
    loss = (weights * probe(weights)).sum() + sum((finite(out[k]) * probe(out[k])).sum() for k in OUTPUTS)
    loss.backward()
    return weights.detach(), {k: out[k].detach() for k in OUTPUTS}, leaves["sigmas"].grad, leaves["rgbs"].grad


@needs_kernel
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_a_constant_density_gives_the_closed_form(dtype):
    # density c on [2, 6] cut into 64 uneven intervals: T(s) = exp(-c (s - 2)), so w_i = T(start_i) - T(end_i),
    # opacity 1 - exp(-4c), colour k_i per interval, depth sum w_i t_i / opacity
    c, B, S = 0.7, 3, 64
    edges = torch.cat([torch.tensor([2.0]), (2 + 4 * torch.rand(S - 1, generator=torch.Generator().manual_seed(2)))
                       .sort().values, torch.tensor([6.0])]).double()
    starts, ends = edges[:-1].expand(B, S), edges[1:].expand(B, S)
    colours = torch.rand(B, S, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    background = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64)
    exact_w = torch.exp(-c * (starts - 2)) - torch.exp(-c * (ends - 2))
    exact_opacity = 1 - math.exp(-4 * c)
    exact_rgb = (exact_w[..., None] * colours).sum(1) + (1 - exact_opacity) * background
    exact_depth = (exact_w * starts).sum(1) / exact_opacity
    assert fused_kernel(starts.to(dtype), colours.to(dtype), starts.to(dtype), ends.to(dtype), starts.to(dtype),
                        background.to(dtype)) is FUSED
    weights, out = rendered(torch.full((B, S), c, dtype=dtype), colours.to(dtype), starts.to(dtype), ends.to(dtype),
                            starts.to(dtype), background.to(dtype), far=6.0)
    tol = 1e-12 if dtype == torch.float64 else 2e-6
    torch.testing.assert_close(weights.double(), exact_w, atol=tol, rtol=0)
    torch.testing.assert_close(out["opacity"].double(), torch.full((B,), exact_opacity, dtype=torch.float64),
                               atol=tol, rtol=0)
    torch.testing.assert_close(out["rgb"].double(), exact_rgb, atol=tol, rtol=0)
    torch.testing.assert_close(out["depth"].double(), exact_depth, atol=10 * tol, rtol=0)


@needs_kernel
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_outputs_and_gradients_equal_the_torch_paths(dtype):
    inputs = rays(40, 33, dtype)
    inputs["sigmas"][0] = 0  # a ray that absorbs nothing: depth at far, colour the background
    inputs["sigmas"][1, 5] = math.inf  # an opaque interval: nothing behind it weighs anything
    inputs["ends"][2, 7] = inputs["starts"][2, 7]  # a zero-width interval absorbs nothing
    inputs["sigmas"][2, 7] = 5.0
    fused = outputs_and_grads(rendered, inputs)
    reference = outputs_and_grads(torch_path, inputs)
    tol = {"atol": 1e-12, "rtol": 1e-12} if dtype == torch.float64 else {"atol": 2e-5, "rtol": 2e-5}
    torch.testing.assert_close(fused[0], reference[0], **tol)
    for k in OUTPUTS:
        torch.testing.assert_close(fused[1][k], reference[1][k], **tol)
    torch.testing.assert_close(fused[2], reference[2], **tol)  # the densities' gradient
    torch.testing.assert_close(fused[3], reference[3], **tol)  # the colours'
    assert fused[1]["depth"][0] == 6.0 and fused[1]["opacity"][0] == 0
    assert (fused[0][1, 6:] == 0).all() and fused[2][1, 5] == 0  # behind the opaque interval; inf's gradient
    assert fused[0][2, 7] == 0 and fused[2][2, 7] == 0
    assert torch.isfinite(fused[2]).all() and torch.isfinite(fused[3]).all()


@needs_kernel
def test_the_gradients_are_the_derivatives():
    inputs = rays(4, 6, seed=5)
    inputs["sigmas"] = inputs["sigmas"] + 0.1  # away from 0, where tau's gradient stops
    inputs["ends"][:, -1] = 6.0  # finite intervals: a finite difference sees every density

    def outputs(sigmas, rgbs):
        weights, out = rendered(sigmas, rgbs, inputs["starts"], inputs["ends"], inputs["t"], inputs["background"],
                                far=6.0)
        return weights, out["rgb"], out["opacity"], out["depth"], out["disparity"]

    assert torch.autograd.gradcheck(outputs, (inputs["sigmas"].requires_grad_(), inputs["rgbs"].requires_grad_()))


@needs_kernel
def test_empty_batches_one_sample_and_nan_densities():
    for B, S in ((0, 8), (3, 1)):
        inputs = rays(B, S)
        fused = outputs_and_grads(rendered, inputs)
        reference = outputs_and_grads(torch_path, inputs)
        torch.testing.assert_close(fused[0], reference[0], atol=1e-12, rtol=0)
        torch.testing.assert_close(fused[2], reference[2], atol=1e-12, rtol=0)
    inputs = rays(3, 8)
    inputs["sigmas"][1, 2] = math.nan  # stays NaN, for the guards to see, and stays in its own ray
    weights, out = rendered(**inputs, far=6.0)
    assert weights[1, 2:].isnan().all() and out["rgb"][1].isnan().all()
    assert not weights[[0, 2]].isnan().any() and not out["rgb"][[0, 2]].isnan().any()


def test_the_torch_path_runs_where_the_kernel_does_not_compute_what_is_asked(monkeypatch):
    inputs = rays(5, 7, torch.float32)
    starts = inputs["starts"].clone().requires_grad_()  # a refined camera moves the intervals: their gradient
    assert fused_kernel(inputs["sigmas"], inputs["rgbs"], starts, inputs["ends"], inputs["t"],
                        inputs["background"]) is None
    weights, out = rendered(**{**inputs, "starts": starts}, far=6.0)
    out["rgb"].sum().backward()
    assert starts.grad is not None and starts.grad.abs().sum() > 0
    with torch.no_grad():  # no gradient asked: the kernel computes it
        assert fused_kernel(inputs["sigmas"], inputs["rgbs"], starts, inputs["ends"], inputs["t"],
                            inputs["background"]) is FUSED
    half = {k: v.half() for k, v in inputs.items()}
    assert fused_kernel(*half.values()) is None
    meta = {k: v.to("meta") for k, v in inputs.items()}
    assert fused_kernel(*meta.values()) is None  # any device but the CPU: the torch path (a GPU's)
    monkeypatch.setenv(kernels.SWITCH, "off")
    assert fused_kernel(*inputs.values()) is None


@needs_kernel
def test_a_wrong_call_is_one_line():
    inputs = rays(4, 5, torch.float32)
    args = list(inputs.values())
    with pytest.raises(RuntimeError, match=r"composite: sigmas is not contiguous"):
        FUSED.forward(args[0].T.contiguous().T, *args[1:], 6.0)
    with pytest.raises(RuntimeError, match=r"composite: rgbs is Double, not Float as sigmas"):
        FUSED.forward(args[0], args[1].double(), *args[2:], 6.0)
    with pytest.raises(RuntimeError, match=r"composite: sigmas, starts, ends and t must be \[B, S\] alike"):
        FUSED.forward(args[0], args[1], args[2][:, :4].contiguous(), *args[3:], 6.0)
    with pytest.raises(RuntimeError, match=r"composite: sigmas is Half, not float32 or float64"):
        FUSED.forward(*(a.half() for a in args), 6.0)
    with pytest.raises(RuntimeError) as error:
        FUSED.forward(args[0], args[1][..., :2].contiguous(), *args[2:], 6.0)
    assert "rgbs must be [B, S, 3]" in str(error.value).splitlines()[0]


@needs_kernel
def test_the_renderer_gives_the_same_pixels_and_gradients_on_both_paths(monkeypatch):
    from nerfexp.nerf.encodings import PositionalEncoding
    from nerfexp.nerf.fields import NeRFField, ViewMLPHead
    from nerfexp.nerf.hierarchy import HierarchyChoice
    from nerfexp.nerf.volume_renderer import VolumeRenderer

    def field():
        head = functools.partial(ViewMLPHead, direction_encoding=PositionalEncoding(2), hidden=16)
        return NeRFField(PositionalEncoding(4), head, depth=2, width=32, skips=(), density_activation="softplus")

    torch.manual_seed(0)
    renderer = VolumeRenderer(field, HierarchyChoice(True, 16, 16, 0), near=2.0, far=6.0)
    origins = torch.randn(64, 3) * 0.1 + torch.tensor([0.0, 0.0, 4.0])
    directions = torch.nn.functional.normalize(torch.randn(64, 3) * 0.2 + torch.tensor([0.0, 0.0, -1.0]), dim=-1)

    def render_and_grads():
        renderer.zero_grad()
        torch.manual_seed(1)  # the same stratified jitter on both paths
        out = renderer(origins, directions, deterministic=False)
        (out["coarse"]["rgb"].square().sum() + out["fine"]["rgb"].square().sum()
         + out["fine"]["depth"].sum()).backward()
        return out, [p.grad.clone() for p in renderer.parameters()]

    assert renderer.kernels() == (compositing.KERNEL,)
    fused, fused_grads = render_and_grads()
    monkeypatch.setenv(kernels.SWITCH, "off")
    reference, reference_grads = render_and_grads()
    for name in ("coarse", "fine"):
        for k in ("rgb", "depth", "opacity", "weights"):
            torch.testing.assert_close(fused[name][k], reference[name][k], atol=1e-5, rtol=1e-5)
    for mine, theirs in zip(fused_grads, reference_grads, strict=True):
        torch.testing.assert_close(mine, theirs, atol=1e-4, rtol=1e-4)
