"""Test-time fits with the networks frozen: one small vector (a test image's appearance code, its camera's pose
correction) fitted by Adam to the image's own pixels, as NeRF in the Wild and BARF evaluate. Only the vector is
differentiated, so no network's weight or gradient changes."""

from collections.abc import Callable
from typing import ClassVar

import torch
from torch import Tensor

from nerfexp.domains import COUNT, LEARNING_RATE, Rule


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


class FrozenFit:
    """A test-time fit's settings, the networks frozen (``fit_frozen``): ``steps`` steps of Adam at learning rate
    ``lr`` on the vector alone, each on ``rays`` of the image's fitting pixels drawn with replacement from a
    generator seeded with the image's index (the same pixels whatever else ran before). Its subclasses say what
    the vector is, where it starts, and their defaults (``nerfexp.nerf.appearance.CodeFit``,
    ``nerfexp.nerf.poses.PoseFit``)."""

    DOMAINS: ClassVar[dict[str, Rule]] = {"steps": COUNT, "lr": LEARNING_RATE, "rays": COUNT}

    def __init__(self, steps: int, lr: float, rays: int):
        self.steps = steps
        self.lr = lr
        self.rays = rays

    def fit(self, loss: Callable[[Tensor, Tensor], Tensor], start: Tensor, n_pixels: int, seed: int,
            progress: Callable[[int], None] | None = None) -> Tensor:
        """The vector [D] fitted from ``start`` [D] (``fit_frozen`` with this fit's ``steps``, ``lr`` and
        ``rays``): ``loss(pixels [R], vector [D])`` is the scalar loss of the fitting pixels ``pixels`` (indices
        < ``n_pixels``); ``progress(steps done)`` after each step, where given."""
        return fit_frozen(loss, start, n_pixels, seed, steps=self.steps, lr=self.lr, rays=self.rays,
                          progress=progress)
