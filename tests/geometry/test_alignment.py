"""The alignment of estimated to true cameras: a known similarity recovered exactly, rotation angles against
closed forms, and the errors of cameras perturbed by known amounts (``nerfexp.data.pose_noise``)."""

import math

import pytest
import torch

from nerfexp.data.pose_noise import check_pose_noise, perturbed_poses
from nerfexp.errors import ConfigError
from nerfexp.geometry.alignment import camera_radius, pose_errors, rotation_angle, umeyama
from nerfexp.geometry.cameras import look_at
from nerfexp.nerf.poses import so3_exp


def ring_cameras(n: int = 12) -> torch.Tensor:
    """n cameras on a tilted ring of radius 4 looking at the origin: c2w [n, 4, 4] float64."""
    angles = torch.arange(n, dtype=torch.float64) * 2 * math.pi / n
    eyes = torch.stack([4 * torch.cos(angles), 4 * torch.sin(angles), 1.0 + torch.sin(3 * angles)], -1)
    return look_at(eyes, torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))


def test_umeyama_recovers_a_known_similarity():
    generator = torch.Generator().manual_seed(0)
    x = torch.randn(20, 3, generator=generator, dtype=torch.float64)
    R = so3_exp(torch.tensor([0.3, -1.2, 2.0], dtype=torch.float64))
    s, t = 2.5, torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    found_s, found_R, found_t = umeyama(x, s * x @ R.T + t)
    assert found_s == pytest.approx(s, rel=1e-12)
    assert torch.allclose(found_R, R, atol=1e-12)
    assert torch.allclose(found_t, t, atol=1e-12)
    assert torch.linalg.det(found_R) == pytest.approx(1.0)


def test_umeyama_refuses_points_at_one_place():
    with pytest.raises(ValueError, match="coincide"):
        umeyama(torch.ones(4, 3), torch.randn(4, 3))


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-4, 0.0349, 1.0, 3.0])
def test_rotation_angle_is_the_angle_of_so3_exp(angle):
    w = torch.tensor([0.0, 0.6, 0.8], dtype=torch.float64) * angle
    assert float(rotation_angle(so3_exp(w))) == pytest.approx(angle, rel=1e-9, abs=1e-15)


def test_the_errors_of_cameras_moved_by_a_similarity_are_zero():
    true = ring_cameras()
    R = so3_exp(torch.tensor([0.4, 0.1, -0.7], dtype=torch.float64))
    moved = true.clone()
    moved[:, :3, :3] = R @ true[:, :3, :3]
    moved[:, :3, 3] = 0.5 * true[:, :3, 3] @ R.T + torch.tensor([3.0, 0.0, -1.0], dtype=torch.float64)
    errors = pose_errors(moved, true)
    assert errors["rotation_deg"] < 1e-9 and errors["centre"] < 1e-12
    assert errors["scale"] == pytest.approx(2.0)


def test_perturbed_poses_move_every_camera_but_the_first_by_the_amounts_asked():
    true = ring_cameras()
    noisy = perturbed_poses(true, 2.0, 0.02, seed=3)
    assert torch.equal(noisy[0], true[0])
    angles = torch.rad2deg(rotation_angle(noisy[1:, :3, :3] @ true[1:, :3, :3].transpose(-1, -2)))
    shifts = torch.linalg.vector_norm(noisy[1:, :3, 3] - true[1:, :3, 3], dim=-1)
    assert torch.allclose(angles, torch.full_like(angles, 2.0), atol=1e-9)
    assert torch.allclose(shifts, torch.full_like(shifts, 0.02 * camera_radius(true)), atol=1e-12)
    assert torch.equal(perturbed_poses(true, 2.0, 0.02, seed=3), noisy)  # seeded
    assert not torch.equal(perturbed_poses(true, 2.0, 0.02, seed=4), noisy)
    errors = pose_errors(noisy, true)  # the alignment absorbs a little of the noise: at most what was put in
    assert 1.0 < errors["rotation_deg"] <= 2.0


@pytest.mark.parametrize("value", [
    [2], [2, -1], ["a", 1], [float("nan"), 0.1], 3, [True, 0.1],
    [1e9, 1e9],  # every camera moved 10^9 radii away: scored as any other run, a number that meant nothing
    [180.5, 0.02], [2, 1.01], [10 ** 400, 0],  # past the largest turn, past the cameras' radius; a whole number too
])                                             # large for a float, compared, never converted
def test_a_bad_pose_noise_is_one_line_naming_the_key(value):
    with pytest.raises(ConfigError, match=r"^datamodule.pose_noise=.*: expected \[degrees, fraction of the cameras' "
                                          r"radius\], degrees a finite number in \[0, 180\] and fraction one in "
                                          r"\[0, 1\], or null"):
        check_pose_noise(value)


@pytest.mark.parametrize(("value", "expected"), [(None, None), ([2, 0.02], (2.0, 0.02)), ([0, 0], (0.0, 0.0)),
                                                 ([180, 1], (180.0, 1.0))])
def test_a_pose_noise_within_its_bounds_is_read_as_degrees_and_a_fraction(value, expected):
    assert check_pose_noise(value) == expected


def test_the_largest_turn_and_shift_move_a_camera_by_exactly_that_much():
    # 180 degrees: the largest turn (no other angle is a larger one, nor a turn about another axis by more); a shift
    # of the cameras' radius puts a camera as far from its pose as the farthest camera is from their centroid
    true = ring_cameras()
    noisy = perturbed_poses(true, 180.0, 1.0, seed=0)
    angles = torch.rad2deg(rotation_angle(noisy[1:, :3, :3] @ true[1:, :3, :3].transpose(-1, -2)))
    shifts = torch.linalg.vector_norm(noisy[1:, :3, 3] - true[1:, :3, 3], dim=-1)
    assert torch.allclose(angles, torch.full_like(angles, 180.0), atol=1e-6)
    assert torch.allclose(shifts, torch.full_like(shifts, camera_radius(true)), atol=1e-12)
