"""A colour field's samples to pixels: the quadrature weights and the composite (``nerfexp.nerf.quadrature``'s
``render_weights`` then ``composite``), by the fused CPU kernel (``nerfexp.kernels``, composite.cpp) where it
computes them, else by those torch functions, which stay the reference it is tested against.

The kernel runs each ray's weights, colour, opacity and depth in one pass, and their gradients with respect to the
densities and colours in another: on a CPU the torch path is some 30 small operators forward and more backward,
each a pass over the [rays, samples] tensors, for every network of every step (docs/acceleration.md).
"""

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from nerfexp.kernels import kernel
from nerfexp.nerf.quadrature import composite, render_weights

KERNEL = "composite"


class _FusedComposite(torch.autograd.Function):
    """``rendered``'s outputs by the kernel: (weights [B, S], rgb [B, 3], opacity [B], depth [B]); the gradients
    of the densities [B, S] and colours [B, S, 3], none of the intervals, t or the background (``fused_kernel``
    runs it only where those need none)."""

    @staticmethod
    def forward(ctx, sigmas: Tensor, rgbs: Tensor, starts: Tensor, ends: Tensor, t: Tensor, background: Tensor,
                far: float, fused) -> tuple[Tensor, ...]:
        weights, rgb, opacity, depth, after = fused.forward(sigmas, rgbs, starts, ends, t, background, far)
        ctx.save_for_backward(sigmas, rgbs, starts, ends, t, background, weights, after, opacity, depth)
        ctx.fused = fused
        ctx.set_materialize_grads(False)  # an output without a gradient comes as None: the kernel reads zeros
        return weights, rgb, opacity, depth

    @staticmethod
    @once_differentiable
    def backward(ctx, g_weights: Tensor | None, g_rgb: Tensor | None, g_opacity: Tensor | None,
                 g_depth: Tensor | None):
        grads = [None if g is None else g.contiguous() for g in (g_weights, g_rgb, g_opacity, g_depth)]
        grad_sigmas, grad_rgbs = ctx.fused.backward(*ctx.saved_tensors, *grads)
        return grad_sigmas, grad_rgbs, None, None, None, None, None, None


def fused_kernel(sigmas: Tensor, rgbs: Tensor, starts: Tensor, ends: Tensor, t: Tensor, background: Tensor):
    """The kernel where it computes ``rendered``: every tensor on the CPU, of one dtype, float32 or float64,
    [B, S] samples (rgbs [B, S, 3]), gradients asked of the densities and colours only (the intervals, t and the
    background need none: a camera that is refined moves them, and the torch path differentiates that), not
    traced by ``torch.compile``; else None (the torch path)."""
    tensors = (sigmas, rgbs, starts, ends, t, background)
    if (any(x.device.type != "cpu" or x.dtype != sigmas.dtype for x in tensors)
            or sigmas.dtype not in (torch.float32, torch.float64) or sigmas.dim() != 2 or rgbs.shape[-1:] != (3,)
            or (torch.is_grad_enabled() and any(x.requires_grad for x in (starts, ends, t, background)))
            or torch.compiler.is_compiling()):
        return None
    return kernel(KERNEL)


def rendered(sigmas: Tensor, rgbs: Tensor, starts: Tensor, ends: Tensor, t: Tensor, background: Tensor,
             far: float) -> tuple[Tensor, dict[str, Tensor]]:
    """The interval weights [B, S] of densities ``sigmas`` [B, S] over intervals [``starts``, ``ends``] [B, S] (in
    distance units; ``render_weights``), and the rays' ``composite`` of colours ``rgbs`` [B, S, 3] at samples ``t``
    [B, S] over ``background`` [3] (cast to the rays' dtype), rays that absorb nothing at depth ``far``: a dict of
    ``rgb`` [B, 3], ``depth``, ``disparity``, ``opacity`` [B], as ``composite`` returns it."""
    background = background.to(sigmas.dtype)
    fused = fused_kernel(sigmas, rgbs, starts, ends, t, background)
    if fused is None:
        weights, _ = render_weights(sigmas, starts, ends)
        return weights, composite(weights, rgbs, t, background, far)
    contiguous = (x.contiguous() for x in (sigmas, rgbs, starts, ends, t, background))
    weights, rgb, opacity, depth = _FusedComposite.apply(*contiguous, far, fused)
    return weights, {"rgb": rgb, "depth": depth, "disparity": torch.reciprocal(depth), "opacity": opacity}
