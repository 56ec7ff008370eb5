"""Modules that work inside the scene's axis-aligned box: the occupancy grid and the hash grid encoding.

``aabb`` [2, 3] is the box (lower corner, upper corner). It is a buffer, so checkpoints keep it, given in
config (``data.aabb``) or set once from the scene when training starts (``NeRFModule.on_train_start``).
"""

from collections.abc import Sequence

import torch
from torch import Tensor, nn


class Bounded(nn.Module):
    """Holds ``aabb`` [2, 3], NaN until ``set_bounds``; ``has_bounds`` is known on the host, so that
    rendering never waits for the device to say whether the box is set."""

    def __init__(self, aabb: Sequence[Sequence[float]] | None = None):
        super().__init__()
        self.register_buffer("aabb", torch.full((2, 3), torch.nan))
        self._bounded = False
        self.register_load_state_dict_post_hook(Bounded._after_load)
        if aabb is not None:
            self.set_bounds(torch.as_tensor(aabb, dtype=torch.float32))

    @property
    def has_bounds(self) -> bool:
        return self._bounded

    @staticmethod
    def _after_load(module: "Bounded", incompatible_keys) -> None:
        module._bounded = bool(torch.isfinite(module.aabb).all())  # the checkpoint's box, if it had one

    def set_bounds(self, aabb: Tensor) -> None:
        """Set the box [2, 3] (lower, upper corner), lower < upper on every axis."""
        if aabb.shape != (2, 3) or not torch.isfinite(aabb).all() or not (aabb[0] < aabb[1]).all():
            raise ValueError(f"{type(self).__name__} bounds: expected [[x0, y0, z0], [x1, y1, z1]] with finite "
                             f"x0 < x1, y0 < y1, z0 < z1, got {aabb.tolist()}")
        self.aabb.copy_(aabb)
        self._bounded = True

    def require_bounds(self) -> None:
        if not self._bounded:
            raise RuntimeError(f"{type(self).__name__} has no bounds: set data.aabb, or train (the module sets "
                               "them from the scene when training starts)")
