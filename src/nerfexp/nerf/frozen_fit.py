"""Test-time fits with the networks frozen: one small vector (a test image's appearance code, its camera's pose
correction) fitted by Adam to the image's own pixels, as NeRF in the Wild and BARF evaluate. Only the vector is
differentiated, so no network's weight or gradient changes."""

from collections.abc import Callable

import torch
from torch import Tensor


def fit_frozen(loss: Callable[[Tensor, Tensor], Tensor], start: Tensor, n_pixels: int, seed: int, *, steps: int,
               lr: float, rays: int, progress: Callable[[int], None] | None = None) -> Tensor:
    """The vector [D] fitted from ``start`` [D]: ``steps`` steps of Adam at learning rate ``lr``, each on
    ``rays`` fitting pixels (indices < ``n_pixels``) drawn with replacement from a generator seeded with ``seed``
    (the same pixels whatever ran before); ``loss(pixels [R], vector [D])`` is their scalar loss. The gradient is
    taken with ``torch.autograd.grad`` with respect to the vector alone. Where no pixel drawn saw the vector (an
    occupancy grid skipped every sample, or the loss does not depend on it) the step is skipped.
    ``progress(done)``, where given, is called after each step with the steps done so far (a progress bar's)."""
    vector = start.detach().clone().requires_grad_()
    optimizer = torch.optim.Adam([vector], lr=lr)
    generator = torch.Generator().manual_seed(seed)
    for done in range(1, steps + 1):
        pixels = torch.randint(n_pixels, (rays,), generator=generator)
        value = loss(pixels, vector)
        (grad,) = torch.autograd.grad(value, vector, allow_unused=True) if value.requires_grad else (None,)
        if grad is not None:
            vector.grad = grad
            optimizer.step()
        if progress is not None:
            progress(done)
    return vector.detach()
