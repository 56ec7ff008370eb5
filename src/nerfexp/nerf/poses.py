"""Camera refinement: a learned pose correction per training image (the ``camera_opt`` axis).

Conventions of this module: ``w`` [..., 3] is a rotation vector (axis times angle, radians, an element of
so(3)); ``R`` [..., 3, 3] a rotation matrix; ``delta`` [N, 6] a correction per view, (w, t), its rotation
vector then its translation t in scene units. A correction (w, t) of a camera turns its rays about the
camera's centre and moves the centre: origin o -> o + t, direction d -> exp(w) d (nerfstudio's ``SO3xR3``),
so that the refined camera-to-world matrix is [exp(w) R_c | c + t] for a camera [R_c | c]. Rotation and
translation are decoupled: a rotation does not move the centre, as it would about the world's origin.
"""

from collections.abc import Callable, Mapping
from typing import ClassVar

import torch
from torch import Tensor, nn

from nerfexp.domains import LEARNING_RATE, NONNEGATIVE_COUNT, Rule
from nerfexp.nerf.frozen_fit import FrozenFit
from nerfexp.nerf.schedules import warmup_exponential_decay


def taylor_threshold(dtype: torch.dtype) -> float:
    """The theta^2 below which ``so3_exp``'s Taylor series (to theta^6) is exact to ``dtype``'s resolution: its
    first omitted term, theta^8 / 9!, below half an ulp of 1 (about 0.38 for float32, 3e-3 for float64)."""
    return (362880 * torch.finfo(dtype).eps / 2) ** 0.25


def skew(w: Tensor) -> Tensor:
    """The cross-product matrix [w]_x [..., 3, 3] of w [..., 3]: [w]_x v = w x v."""
    x, y, z = w.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(*w.shape[:-1], 3, 3)


def so3_exp(w: Tensor) -> Tensor:
    """Rodrigues' formula: w [..., 3] -> R [..., 3, 3] = I + A [w]_x + B [w]_x^2, theta = |w|,
    A = sin(theta) / theta, B = (1 - cos(theta)) / theta^2 = 2 sin^2(theta / 2) / theta^2 (no cancellation).

    Safe by construction at and near theta = 0: below ``taylor_threshold`` A and B are their Taylor series in
    theta^2 (A = 1 - theta^2/6 + theta^4/120 - theta^6/5040, B = 1/2 - theta^2/24 + theta^4/720 -
    theta^6/40320), polynomials whose gradient is exact; the closed forms are evaluated only at theta^2 >=
    the threshold (the other branch's theta replaced by 1), so neither branch divides by zero, in the values
    or in the gradients. exp(0) = I exactly, and its gradient is that of I + [w]_x.

    >>> so3_exp(torch.tensor([0.0, 0.0, torch.pi / 2])).round(decimals=6)  # a quarter turn about z
    tensor([[ 0., -1.,  0.],
            [ 1.,  0.,  0.],
            [ 0.,  0.,  1.]])
    """
    theta2 = (w * w).sum(-1)  # [...]
    small = theta2 < taylor_threshold(w.dtype)
    theta = torch.sqrt(torch.where(small, torch.ones_like(theta2), theta2))  # 1 where the series is used
    taylor_a = 1 - theta2 / 6 * (1 - theta2 / 20 * (1 - theta2 / 42))
    taylor_b = 0.5 - theta2 / 24 * (1 - theta2 / 30 * (1 - theta2 / 56))
    a = torch.where(small, taylor_a, torch.sin(theta) / theta)
    b = torch.where(small, taylor_b, 2 * torch.sin(theta / 2) ** 2 / theta ** 2)
    K = skew(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return eye + a[..., None, None] * K + b[..., None, None] * (K @ K)


def corrected_poses(c2w: Tensor, delta: Tensor) -> Tensor:
    """Cameras c2w [N, 4, 4] corrected by delta [N, 6] (the module's convention): [exp(w) R_c | c + t]."""
    refined = c2w.clone()
    refined[:, :3, :3] = so3_exp(delta[:, :3]) @ c2w[:, :3, :3]
    refined[:, :3, 3] = c2w[:, :3, 3] + delta[:, 3:]
    return refined


def corrected_rays(rotation: Tensor, shift: Tensor, origins: Tensor, directions: Tensor,
                   viewdirs: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor | None]:
    """Rays origins, directions, viewdirs [..., 3] of cameras turned by ``rotation`` [..., 3, 3] about their
    centres and moved by ``shift`` [..., 3] (each broadcast against the rays: one per ray, or one for all):
    (o + t, R d, R viewdir), in the correction's dtype; ``viewdirs`` None stays None."""
    def turned(vectors: Tensor) -> Tensor:
        return (rotation @ vectors.to(rotation.dtype)[..., None]).squeeze(-1)
    return (origins.to(shift.dtype) + shift, turned(directions),
            None if viewdirs is None else turned(viewdirs))


def camera_corrected_rays(delta: Tensor, origins: Tensor, directions: Tensor,
                          viewdirs: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor | None]:
    """The rays [..., 3] of one camera corrected by delta [6] (w, t), in delta's precision (float32) under mixed
    precision too, as ``PoseCorrection.forward``: ``corrected_rays`` with R = exp(w)."""
    with torch.autocast(delta.device.type, enabled=False):
        return corrected_rays(so3_exp(delta[:3]), delta[3:], origins, directions, viewdirs)


class PoseCorrection(nn.Module):
    """A correction (w, t) per training view, all zero at first (the given poses), applied to the rays of
    each view (``forward``); the first view's is pinned at zero, which fixes the gauge: the frame of the
    reconstruction is that of the first camera, which nothing else would (a rigid motion of every camera with
    the scene renders the same images). ``delta`` [N - 1, 6] holds the other views' corrections.

    Its parameters are the optimizer's group ``camera_opt`` (``parameter_groups``), with their own learning
    rate ``lr``, decaying exponentially to ``lr_final`` over training, ramped up linearly over the first
    ``warmup_steps`` (``lr_factor``: Adam moves every pose by about the rate at each step, and before the scene
    takes shape its gradients point nowhere), without weight decay.
    """

    DOMAINS: ClassVar[dict[str, Rule]] = {
        "lr": LEARNING_RATE,
        "lr_final": LEARNING_RATE,
        "warmup_steps": NONNEGATIVE_COUNT,
    }
    GROUP = "camera_opt"  # the optimizer's parameter group

    @staticmethod
    def WORLD_RAYS(ndc: str, world: str) -> str:
        """It turns and moves world rays: refused with NDC rays (``ndc``; ``world``: how to have world rays)."""
        return f"camera_opt=so3xr3: the corrections move world rays, and {ndc} trains on NDC rays; set {world} to " \
               "refine an LLFF scene's cameras"

    def __init__(self, n_views: int, lr: float, lr_final: float, warmup_steps: int = 0):
        super().__init__()
        if n_views < 1:
            raise ValueError(f"PoseCorrection: expected at least one view, got {n_views}")
        self.n_views = n_views
        self.lr = lr
        self.lr_final = lr_final
        self.warmup_steps = warmup_steps
        self.delta = nn.Parameter(torch.zeros(n_views - 1, 6))

    def corrections(self) -> Tensor:
        """Every view's correction [N, 6], the first's zero."""
        return torch.cat([self.delta.new_zeros(1, 6), self.delta])

    def forward(self, origins: Tensor, directions: Tensor, views: Tensor,
                viewdirs: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor | None]:
        """Rays of views ``views`` [B] (long): origins, directions, viewdirs [B, 3] -> corrected (o + t,
        exp(w) d, exp(w) viewdir); ``viewdirs`` None stays None. Computed in the parameters' precision (float32)
        under mixed precision too: a bf16 rotation would turn rays by tenths of a degree, the size of the errors
        being corrected."""
        with torch.autocast(origins.device.type, enabled=False):
            delta = self.corrections()  # [N, 6]
            return corrected_rays(so3_exp(delta[:, :3])[views], delta[views, 3:], origins, directions, viewdirs)

    @torch.no_grad()
    def refined(self, c2w: Tensor) -> Tensor:
        """The training cameras c2w [N, 4, 4] as corrected (``corrected_poses``), in float64."""
        return corrected_poses(c2w.double(), self.corrections().double())

    def parameter_groups(self) -> dict[str, dict]:
        return {self.GROUP: {"params": [self.delta], "lr": self.lr, "weight_decay": 0.0}}

    def lr_factor(self, step: int, max_steps: int) -> float:
        """The group's learning rate at ``step`` over its ``lr``: min(1, (step + 1) / warmup_steps) (lr_final /
        lr)^(step / max_steps)."""
        return warmup_exponential_decay(step, max_steps, self.lr_final / self.lr, self.warmup_steps)


class PoseFit(FrozenFit):
    """A test camera refined with the networks frozen (``test_cameras=refined``, BARF's evaluation): a correction
    (w, t) [6] of the image's rays (``corrected_rays``, the convention of ``PoseCorrection``), from zero,
    fitted by ``steps`` steps of Adam at ``lr`` (radians and scene units alike), each on ``rays`` of the image's
    fitting pixels drawn from a generator seeded with the image's index (``nerfexp.nerf.frozen_fit.FrozenFit``)."""

    @staticmethod
    def RAYS(config: Mapping) -> tuple[int, tuple[str, ...], str]:
        """A step renders ``rays`` rays, their outputs kept for the backward pass to the correction."""
        return config["rays"], ("rays",), "a step of the test cameras' fit"

    @staticmethod
    def WORLD_RAYS(ndc: str, world: str) -> str:
        """It turns and moves world rays: refused with NDC rays (``ndc``; ``world``: how to have world rays)."""
        return f"test_cameras=refined: the fit turns and moves world rays, and {ndc} scores NDC rays; set {world}, " \
               "or test_cameras=given"

    def __init__(self, steps: int = 100, lr: float = 1e-3, rays: int = 1024):
        super().__init__(steps, lr, rays)

    def __call__(self, loss: Callable[[Tensor, Tensor], Tensor], n_pixels: int, seed: int,
                 device: torch.device | None = None, progress: Callable[[int], None] | None = None) -> Tensor:
        """The correction [6] (float32) fitted from zero: ``loss(pixels [R], delta [6])`` is the scalar loss of
        the fitting pixels ``pixels`` (indices < ``n_pixels``) rendered through the rays ``delta`` corrects;
        ``progress(steps done)`` after each step, where given (``fit_frozen``)."""
        return self.fit(loss, torch.zeros(6, device=device), n_pixels, seed, progress)
