import math

import pytest
import torch

from nerfexp.geometry.cameras import camera_rays, centre_spread, focal_from_fov, look_at
from nerfexp.geometry.lenses import Intrinsics


def _hit(origins, directions, point):
    """Distance from ``point`` to each ray: [...]."""
    to_point = point - origins
    along = (to_point * directions).sum(-1, keepdim=True)
    return torch.linalg.vector_norm(to_point - along * directions, dim=-1)


def test_ray_through_a_known_pixel_hits_a_known_point():
    # Camera at (0, 0, 4) looking down -z (identity rotation), 100 x 100 pixels, focal 200.
    # The point (0.31, -0.21, 0) is at depth 4: it projects to x = 50 + 200 * 0.31 / 4 = 65.5,
    # y = 50 + 200 * 0.21 / 4 = 60.5, the centre of pixel (row 60, column 65).
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[2, 3] = 4.0
    origins, directions = camera_rays(c2w, 100, 100, Intrinsics.pinhole(200.0, 100, 100))
    distance = _hit(origins, directions, torch.tensor([0.31, -0.21, 0.0], dtype=torch.float64))
    assert distance[60, 65] < 1e-12
    assert torch.argmin(distance).item() == 60 * 100 + 65
    torch.testing.assert_close(torch.linalg.vector_norm(directions, dim=-1), torch.ones(100, 100, dtype=torch.float64))


def test_look_at_camera_sees_the_target_in_the_image_centre():
    eye = torch.tensor([3.0, -2.0, 1.5], dtype=torch.float64)
    c2w = look_at(eye, torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    R = c2w[:3, :3]
    torch.testing.assert_close(R.T @ R, torch.eye(3, dtype=torch.float64))
    assert torch.isclose(torch.linalg.det(R), torch.tensor(1.0, dtype=torch.float64))
    assert c2w[2, 1] > 0  # the camera's up has a positive world-z component
    # With an even image size the target lies on the corner shared by the four central pixels.
    origins, directions = camera_rays(c2w, 8, 8, Intrinsics.pinhole(10.0, 8, 8))
    distance = _hit(origins, directions, torch.zeros(3, dtype=torch.float64))
    centre = distance[3:5, 3:5]
    torch.testing.assert_close(centre, centre[0, 0].expand(2, 2))
    assert distance.min() == centre.min()


def test_focal_from_fov():
    # 90 degrees across 100 pixels: tan(45 deg) = 1, so f = 50.
    assert abs(focal_from_fov(100, torch.pi / 2) - 50.0) < 1e-12


@pytest.mark.parametrize(("centres", "spread"), [
    ([[0, 0, 0], [2, 0, 0]], 1.0),  # each 1 from their mean (1, 0, 0)
    ([[1, 2, 3]], 0.0),  # one camera
    ([[1, 2, 3], [1, 2, 3], [1, 2, 3]], 0.0),  # cameras at one point
    ([[-1, 0, 0], [1, 0, 0], [0, 3, 0], [0, -3, 0]], math.sqrt((1 + 1 + 9 + 9) / 4)),  # mean at the origin
])
def test_the_spread_of_camera_centres_is_their_rms_distance_from_their_mean(centres, spread):
    centres = torch.tensor(centres, dtype=torch.float64)
    assert centre_spread(centres) == pytest.approx(spread, abs=1e-15)
    rotation, _ = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)))
    moved = 2.5 * centres @ rotation.T + torch.tensor([4.0, -1.0, 7.0], dtype=torch.float64)  # a similarity
    assert centre_spread(moved) == pytest.approx(2.5 * spread, abs=1e-12)
