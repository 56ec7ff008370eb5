"""Camera paths for rendering videos of a trained scene: an orbit around 360-degree captures, a spiral
in front of forward-facing ones.

Conventions: camera-to-world matrices ``c2w`` [..., 4, 4] in the OpenGL convention of
``nerfexp.geometry.cameras`` (x right, y up, looking down -z); a camera path is [F, 4, 4], one camera
per frame. A camera's "up" is its y axis, ``c2w[..., :3, 1]``; its "back" its z axis, ``c2w[..., :3, 2]``.
"""

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from nerfexp.errors import NerfexpError
from nerfexp.geometry.cameras import look_at


def mean_up(c2w: Tensor) -> Tensor:
    """The cameras' mean up direction [3] (unit): the normalized sum of their y axes (LLFF's convention)."""
    return F.normalize(c2w[:, :3, 1].sum(0), dim=-1)


def orbit_path(c2w: Tensor, n_frames: int) -> Tensor:
    """``n_frames`` cameras evenly spaced on a circle around the origin, each looking at it: [F, 4, 4].

    For 360-degree captures (cameras ``c2w`` [N, 4, 4] around an object at the origin). The circle lies
    at the cameras' mean distance r from the origin and their mean elevation e above the plane through
    the origin perpendicular to their mean up u (``mean_up``); with a unit basis (a, b) of that plane,
    frame k sits at r (cos e (cos phi_k a + sin phi_k b) + sin e u), phi_k = 2 pi k / F.
    ``a`` points to the camera farthest from the up axis, so the first frame is near that training view.

    Example: cameras at distances 3 and 5, elevations 30 and 50 degrees, z up: a circle of radius
    4 cos 40deg at height 4 sin 40deg.
    """
    up = mean_up(c2w)
    centres = c2w[:, :3, 3]  # [N, 3]
    distances = torch.linalg.vector_norm(centres, dim=-1)  # [N]
    heights = centres @ up  # [N]
    elevation = torch.asin((heights / distances).clamp(-1, 1)).mean()
    across = centres - heights[:, None] * up  # [N, 3]: the centres projected onto the plane
    a = F.normalize(across[torch.linalg.vector_norm(across, dim=-1).argmax()], dim=-1)
    b = torch.linalg.cross(up, a, dim=-1)
    phi = 2 * math.pi * torch.arange(n_frames, dtype=c2w.dtype) / n_frames  # [F]
    ring = torch.cos(phi)[:, None] * a + torch.sin(phi)[:, None] * b  # [F, 3]
    eyes = distances.mean() * (torch.cos(elevation) * ring + torch.sin(elevation) * up)
    return look_at(eyes, torch.zeros(3, dtype=c2w.dtype), up)


def llff_focus_depth(near: float, far: float) -> float:
    """The depth a forward-facing spiral looks at (LLFF's ``render_path_spiral``): the weighted harmonic
    mean 1 / (0.25 / (0.9 near) + 0.75 / (5 far)) of a depth just before the nearest content and one
    well beyond the farthest. Example: near 2, far 6 gives 1 / (0.25 / 1.8 + 0.75 / 30) = 6.08."""
    if not 0 < near < far:
        raise NerfexpError(f"a spiral's focus depth needs depth bounds 0 < near < far, got near={near}, far={far}; "
                           "give it with --focus DEPTH")
    return 1 / (0.25 / (0.9 * near) + 0.75 / (5 * far))


def spiral_path(c2w: Tensor, n_frames: int, focus_depth: float, rotations: float = 2,
                z_rate: float = 0.5) -> Tensor:
    """``n_frames`` cameras on a spiral around the mean camera, all looking at one point: [F, 4, 4].

    For forward-facing captures (LLFF's ``render_path_spiral``). The mean camera sits at the mean centre
    c of ``c2w`` [N, 4, 4], with the mean back axis z and the mean up u made orthonormal (x = u cross z,
    y = z cross x). Radii (r_x, r_y, r_z) are the 90th percentiles of the cameras' |offsets| from c
    along x, y, z. Frame k, at angle theta_k = 2 pi rotations k / F, sits at
    c + r_x cos(theta) x - r_y sin(theta) y - r_z sin(z_rate theta) z and looks at the focus point
    c - focus_depth z (in front of the mean camera), with up u.
    """
    centre = c2w[:, :3, 3].mean(0)
    up = mean_up(c2w)
    back = F.normalize(c2w[:, :3, 2].sum(0), dim=-1)
    right = F.normalize(torch.linalg.cross(up, back, dim=-1), dim=-1)
    basis = torch.stack([right, torch.linalg.cross(back, right, dim=-1), back])  # [3, 3]: rows x, y, z
    radii = torch.quantile((c2w[:, :3, 3] - centre).abs() @ basis.T, 0.9, dim=0)  # [3]
    theta = 2 * math.pi * rotations * torch.arange(n_frames, dtype=c2w.dtype) / n_frames  # [F]
    local = torch.stack([torch.cos(theta), -torch.sin(theta), -torch.sin(z_rate * theta)], -1) * radii  # [F, 3]
    return look_at(centre + local @ basis, centre - focus_depth * back, up)
