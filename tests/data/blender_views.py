"""Small Blender-format test views the data tests write and read back: random images with transparent pixels,
random camera rotations and positions, and the camera angle they are written with."""

import torch

from nerfexp.data.views import Views
from nerfexp.geometry.lenses import Intrinsics

ANGLE = 0.6911112070083618  # camera_angle_x the views are written with


def make_views(n=6, height=6, width=8, seed=0) -> Views:
    g = torch.Generator().manual_seed(seed)
    rgba = torch.rand(n, height, width, 4, generator=g)
    rgba[..., 3] = torch.where(rgba[..., 3] < 0.3, 0.0, rgba[..., 3])  # some fully transparent pixels
    q, _ = torch.linalg.qr(torch.randn(n, 3, 3, generator=g, dtype=torch.float64))
    q = q * torch.linalg.det(q).sign()[:, None, None]  # rotations (det +1), not reflections: camera poses
    c2w = torch.eye(4).repeat(n, 1, 1)
    c2w[:, :3, :3], c2w[:, :3, 3] = q.float(), torch.randn(n, 3, generator=g)
    return Views(rgba=rgba, c2w=c2w, intrinsics=Intrinsics.pinhole(1.0, height, width, (n,)))
