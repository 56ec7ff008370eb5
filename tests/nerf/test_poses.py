"""Camera refinement's pieces against independent truth: so3_exp against float64 closed forms and matrix_exp
(values and gradients, at zero, tiny, small and large angles), the pose correction's gauge and rays."""

import math

import pytest
import torch

from nerfexp.nerf.poses import (
    PoseCorrection,
    camera_corrected_rays,
    corrected_poses,
    skew,
    so3_exp,
    taylor_threshold,
)


def reference_exp(w: torch.Tensor) -> torch.Tensor:
    """exp([w]_x) by torch.matrix_exp in float64: an independent computation (a Pade approximant)."""
    return torch.linalg.matrix_exp(skew(w.double()))


ANGLES = [0.0, 1e-30, 1e-12, 1e-6, 1e-3, 0.05, 0.3, 0.6, 0.62, 1.0, 2.0, 3.0, math.pi - 1e-6]


@pytest.mark.parametrize("angle", ANGLES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_so3_exp_matches_the_matrix_exponential(angle, dtype):
    axis = torch.tensor([0.36, -0.48, 0.8])  # unit: 0.36^2 + 0.48^2 + 0.8^2 = 1
    w = (axis * angle).to(dtype)
    R = so3_exp(w)
    tolerance = 4 * torch.finfo(dtype).eps
    assert R.dtype == dtype
    assert torch.allclose(R.double(), reference_exp(w), atol=tolerance, rtol=0)
    assert torch.allclose((R.T @ R).double(), torch.eye(3, dtype=torch.float64), atol=tolerance, rtol=0)


def test_so3_exp_of_zero_is_exactly_the_identity_with_the_gradient_of_i_plus_the_skew():
    w = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    R = so3_exp(w)
    assert torch.equal(R, torch.eye(3, dtype=torch.float64))
    # d exp([w]_x) / dw at 0 is the generator: dR/dw_k = [e_k]_x, so sum(R * G) has gradient <[e_k]_x, G>
    G = torch.arange(9, dtype=torch.float64).reshape(3, 3)
    (R * G).sum().backward()
    expected = torch.stack([(skew(torch.eye(3, dtype=torch.float64)[k]) * G).sum() for k in range(3)])
    assert torch.equal(w.grad, expected)  # (7 - 5, 2 - 6, 3 - 1): exact, no division anywhere


@pytest.mark.parametrize("angle", [0.0, 1e-8, 1e-4, 0.1, 0.5, 0.62, 1.5, 3.0])
def test_so3_exp_gradients_are_finite_and_match_the_float64_matrix_exponential(angle):
    axis = torch.tensor([0.36, -0.48, 0.8], dtype=torch.float64)
    G = torch.randn(3, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    w = (axis * angle).requires_grad_(True)
    (so3_exp(w) * G).sum().backward()
    w_ref = (axis * angle).requires_grad_(True)
    (reference_exp(w_ref) * G).sum().backward()
    assert torch.isfinite(w.grad).all()
    assert torch.allclose(w.grad, w_ref.grad, atol=1e-12, rtol=1e-10)
    w32 = (axis * angle).float().requires_grad_(True)
    (so3_exp(w32) * G.float()).sum().backward()
    assert torch.isfinite(w32.grad).all()
    assert torch.allclose(w32.grad.double(), w_ref.grad, atol=2e-6, rtol=0)


def test_so3_exp_matches_rodrigues_closed_form_for_a_quarter_turn():
    # a quarter turn about z maps x to y and y to -x: hand-worked
    R = so3_exp(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64))
    expected = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    assert torch.allclose(R, expected, atol=1e-15, rtol=0)


def test_the_taylor_threshold_follows_the_dtype():
    assert 0.3 < taylor_threshold(torch.float32) < 0.4
    assert 2e-3 < taylor_threshold(torch.float64) < 3e-3


def test_the_first_views_correction_is_pinned_and_never_moves():
    correction = PoseCorrection(4, lr=1e-2, lr_final=1e-4)
    assert correction.delta.shape == (3, 6)
    optimizer = torch.optim.Adam(correction.parameter_groups()["camera_opt"]["params"], lr=1e-2)
    generator = torch.Generator().manual_seed(0)
    for _ in range(20):
        views = torch.randint(4, (64,), generator=generator)
        origins, directions = torch.randn(64, 3, generator=generator), torch.randn(64, 3, generator=generator)
        moved, turned, _ = correction(origins, directions, views)
        optimizer.zero_grad()
        (moved.sum() + (turned * torch.randn(64, 3, generator=generator)).sum()).backward()
        optimizer.step()
    full = correction.corrections()
    assert torch.equal(full[0], torch.zeros(6))
    assert (full[1:].abs() > 0).any()  # the others moved
    c2w = torch.eye(4).expand(4, 4, 4).clone()
    assert torch.equal(correction.refined(c2w)[0], torch.eye(4, dtype=torch.float64))


def test_a_correction_turns_rays_about_the_camera_centre_and_moves_it():
    correction = PoseCorrection(2, lr=1e-3, lr_final=1e-5)
    with torch.no_grad():
        correction.delta.copy_(torch.tensor([[0.0, 0.0, math.pi / 2, 0.1, 0.2, 0.3]]))
    origins = torch.tensor([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0]])
    directions = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    moved, turned, viewdirs = correction(origins, directions, torch.tensor([0, 1]), directions)
    assert torch.equal(moved[0], origins[0]) and torch.equal(turned[0], directions[0])  # view 0: untouched
    assert torch.allclose(moved[1], torch.tensor([1.1, 2.2, 3.3]))
    assert torch.allclose(turned[1], torch.tensor([0.0, 1.0, 0.0]), atol=1e-6)  # x turned a quarter about z
    assert torch.allclose(viewdirs, turned)
    # the refined camera renders the corrected rays: its centre moved, its axes turned
    c2w = torch.eye(4).expand(2, 4, 4).clone()
    c2w[:, :3, 3] = origins
    refined = corrected_poses(c2w.double(), correction.corrections().detach().double())
    assert torch.allclose(refined[1, :3, 3].float(), moved[1])
    assert torch.allclose(refined[1, :3, :3].float() @ directions[1], turned[1], atol=1e-6)


def test_the_pose_groups_schedule_decays_from_its_rate_to_its_final_rate():
    correction = PoseCorrection(3, lr=1e-3, lr_final=1e-5)
    group = correction.parameter_groups()["camera_opt"]
    assert (group["lr"], group["weight_decay"]) == (1e-3, 0.0)
    assert correction.lr_factor(0, 100) == 1.0
    assert correction.lr_factor(50, 100) == pytest.approx(0.1)
    assert correction.lr_factor(100, 100) == pytest.approx(1e-2)
    assert correction.lr_factor(500, 100) == pytest.approx(1e-2)


def test_a_correction_needs_a_view():
    with pytest.raises(ValueError, match="at least one view"):
        PoseCorrection(0, lr=1e-3, lr_final=1e-5)


def test_one_cameras_rays_are_corrected_as_the_refined_camera_sees_them_in_float32_under_bf16_autocast():
    """camera_corrected_rays (test_cameras=refined) against the refined camera (corrected_poses, float64): rays of
    a camera [R | c] through directions R v are, corrected by (w, t), those of [exp(w) R | c + t] through the same
    v; under bf16 autocast they are computed as without it (a bf16 turn would miss by tenths of a degree)."""
    generator = torch.Generator().manual_seed(0)
    delta = torch.tensor([0.02, -0.025, 0.015, 0.01, -0.03, 0.02])
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = so3_exp(torch.tensor([0.3, 0.2, -0.1], dtype=torch.float64))
    c2w[:3, 3] = torch.tensor([0.5, -1.0, 4.0], dtype=torch.float64)
    camera_dirs = torch.nn.functional.normalize(torch.randn(5, 7, 3, generator=generator, dtype=torch.float64), dim=-1)
    origins, directions = c2w[:3, 3].expand(5, 7, 3).float(), (camera_dirs @ c2w[:3, :3].T).float()
    refined = corrected_poses(c2w[None], delta[None].double())[0]
    moved, turned, viewdirs = camera_corrected_rays(delta, origins, directions, directions)
    assert torch.allclose(moved.double(), refined[:3, 3].expand(5, 7, 3), atol=1e-6)
    assert torch.allclose(turned.double(), camera_dirs @ refined[:3, :3].T, atol=1e-6)
    assert torch.equal(viewdirs, turned)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        under_autocast = camera_corrected_rays(delta, origins, directions, directions)
    assert all(torch.equal(a, b) for a, b in zip(under_autocast, (moved, turned, viewdirs), strict=True))
    assert camera_corrected_rays(delta, origins, directions)[2] is None
