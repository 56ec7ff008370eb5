"""Camera paths (``nerfexp.geometry.camera_paths``) against cameras placed at known positions."""

import math

import pytest
import torch

from nerfexp.errors import NerfexpError
from nerfexp.geometry.camera_paths import llff_focus_depth, orbit_path, spiral_path
from tests.helpers import cameras_at


def test_an_orbit_circles_at_the_cameras_mean_distance_and_elevation():
    # Distances 3, 5.5, 3, 4.5 (mean 4), elevations 30 and 50 degrees (mean 40), opposite azimuths in
    # pairs of equal elevation (so the mean up is exactly z): the orbit is the circle of radius
    # 4 cos 40deg = 3.064 at height 4 sin 40deg = 2.571.
    cams = cameras_at([3, 5.5, 3, 4.5], [30, 50, 30, 50], [10, 100, 190, 280])
    orbit = orbit_path(cams, 8)
    eyes = orbit[:, :3, 3]
    assert orbit.shape == (8, 4, 4)
    torch.testing.assert_close(eyes[:, 2], torch.full((8,), 4 * math.sin(math.radians(40)), dtype=torch.float64))
    torch.testing.assert_close(eyes[:, :2].norm(dim=-1), torch.full((8,), 4 * math.cos(math.radians(40)),
                                                                     dtype=torch.float64))
    # each camera looks at the origin (its back axis points from the origin to it), z up on screen
    torch.testing.assert_close(orbit[:, :3, 2], eyes / eyes.norm(dim=-1, keepdim=True))
    assert (orbit[:, 2, 1] > 0).all()
    # evenly spaced, 45 degrees apart, counterclockwise about z, starting at the azimuth of the camera
    # farthest from the axis: 100 degrees (5.5 cos 50deg = 3.54 from it; the others 2.89 and 2.60)
    azimuth = torch.deg2rad(100 + 45 * torch.arange(8, dtype=torch.float64))
    ring = torch.stack([azimuth.cos(), azimuth.sin()], -1)
    torch.testing.assert_close(eyes[:, :2], 4 * math.cos(math.radians(40)) * ring)


def test_a_spiral_looks_at_its_focus_point_in_front_of_the_mean_camera():
    # Five forward-facing cameras near z = 0, all looking down -z: the mean camera is at the origin.
    offsets = torch.tensor([[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 0.5, 0.2], [0, -0.5, -0.2]], dtype=torch.float64)
    cams = torch.eye(4, dtype=torch.float64).repeat(5, 1, 1)
    cams[:, :3, 3] = offsets
    spiral = spiral_path(cams, 16, focus_depth=10.0)
    eyes, focus = spiral[:, :3, 3], torch.tensor([0, 0, -10.0], dtype=torch.float64)
    torch.testing.assert_close(spiral[:, :3, 2], (eyes - focus) / (eyes - focus).norm(dim=-1, keepdim=True))
    # radii: 90th percentiles of |offsets| per axis, (1, 0.5, 0.2); two turns in 16 frames, so frame 2 is a
    # quarter turn: frame 0 at (r_x, 0, 0), frame 2 at (0, -r_y, -r_z sin(pi/4))
    torch.testing.assert_close(eyes[0], torch.tensor([1.0, 0, 0], dtype=torch.float64))
    torch.testing.assert_close(eyes[2], torch.tensor([0, -0.5, -0.2 * math.sin(math.pi / 4)], dtype=torch.float64))
    assert (spiral[:, 1, 1] > 0.9).all()  # upright


def test_the_focus_depth_is_llffs_weighted_harmonic_mean_of_the_depth_bounds():
    assert llff_focus_depth(2.0, 6.0) == pytest.approx(1 / (0.25 / 1.8 + 0.75 / 30))  # 6.08
    with pytest.raises(NerfexpError, match="0 < near < far"):
        llff_focus_depth(0.0, 1.0)
