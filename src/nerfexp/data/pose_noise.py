"""Training poses perturbed by known amounts (``datamodule.pose_noise``), to measure what camera refinement
(``camera_opt``) brings back: each training camera but the first turned about its centre by exactly ``degrees``
about a random axis, and its centre moved by exactly ``fraction`` of the cameras' radius
(``nerfexp.geometry.alignment.camera_radius``) in a random direction, both drawn from ``seed``.

The first camera keeps its pose: camera refinement pins the first view's correction (the gauge,
``nerfexp.nerf.poses.PoseCorrection``), so the reconstruction stays in the true frame, where the test views
are scored.
"""

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from nerfexp.domains import Rule, breaks, is_real, optional
from nerfexp.errors import ConfigError
from nerfexp.geometry.alignment import camera_radius
from nerfexp.nerf.poses import corrected_poses

# The largest turn: one of more than 180 degrees about an axis is one of less about the opposite axis, which the
# random axis draws as often, so no larger angle is another perturbation
MAX_DEGREES = 180
# The largest shift, in the cameras' radius: a camera moved by the radius may already land on the rig's centre or
# past its far side, no longer near the pose it perturbs (camera refinement recovers errors of a few hundredths);
# a shift far beyond it moves every camera out of the scene it is to see, and the run's scores mean nothing
MAX_FRACTION = 1
POSE_NOISE: Rule = (f"[degrees, fraction of the cameras' radius], degrees a finite number in [0, {MAX_DEGREES}] and "
                    f"fraction one in [0, {MAX_FRACTION}]",
                    lambda v: isinstance(v, list) and len(v) == 2 and all(is_real(x) for x in v)
                    and 0 <= v[0] <= MAX_DEGREES and 0 <= v[1] <= MAX_FRACTION)
POSE_NOISE_SETTING = optional(POSE_NOISE, "the poses as the data gives them")  # datamodule.pose_noise


def random_directions(n: int, generator: torch.Generator) -> Tensor:
    """n unit vectors [n, 3] uniform on the sphere (normalized Gaussians, float64)."""
    v = torch.randn(n, 3, generator=generator, dtype=torch.float64)
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(torch.finfo(v.dtype).tiny)


def perturbed_poses(c2w: Tensor, degrees: float, fraction: float, seed: int) -> Tensor:
    """The cameras c2w [N, 4, 4] perturbed as the module's docstring says (in c2w's dtype): camera n > 0 gets
    the correction (w_n, t_n), |w_n| = ``degrees`` in radians, |t_n| = ``fraction`` x radius, directions
    from a generator seeded with ``seed``; camera 0 unchanged."""
    generator = torch.Generator().manual_seed(seed)
    n = len(c2w)
    axes, shifts = random_directions(n, generator), random_directions(n, generator)
    delta = torch.cat([axes * math.radians(degrees), shifts * fraction * camera_radius(c2w)], -1)
    delta[0] = 0
    return corrected_poses(c2w.double(), delta).to(c2w.dtype)


def check_pose_noise(value: object) -> tuple[float, float] | None:
    """``datamodule.pose_noise`` as (degrees, fraction), or None; a ConfigError where it breaks
    ``POSE_NOISE_SETTING`` (the settings check says the same before a run starts)."""
    numbers = list(value) if isinstance(value, Sequence) and not isinstance(value, str) else value
    if (wanted := breaks(POSE_NOISE_SETTING, numbers)) is not None:
        raise ConfigError(f"datamodule.pose_noise={value}: expected {wanted}")
    return None if numbers is None else (float(numbers[0]), float(numbers[1]))
