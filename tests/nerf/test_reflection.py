import math

import numpy as np
import pytest
import scipy.special
import torch

from nerfexp.nerf.fields import sh_basis
from nerfexp.nerf.reflection import (
    ReflectionViewDependence,
    _unit,
    ide_degrees,
    integrated_directional_encoding,
    linear_to_srgb,
    normal_penalties,
    real_sh_basis,
    reflect,
)


def random_directions(n, dtype=torch.float64, seed=0):
    generator = torch.Generator().manual_seed(seed)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=generator, dtype=dtype), dim=-1)
    poles_and_equator = torch.tensor([[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, -1, 0]], dtype=dtype)
    return torch.cat([d, poles_and_equator])


def scipy_real_sh(directions, ell, m):
    # Real SH from scipy's complex Y_l^m (Condon-Shortley phase included): sqrt 2 Re Y_l^m for m > 0,
    # sqrt 2 Im Y_l^|m| for m < 0, Y_l^0 for m = 0; the convention of fields.sh_basis.
    x, y, z = directions.double().numpy().T
    theta = np.arccos(np.clip(z, -1, 1))
    phi = np.mod(np.arctan2(y, x), 2 * np.pi)
    complex_y = scipy.special.sph_harm_y(ell, abs(m), theta, phi)
    if m == 0:
        return complex_y.real
    return math.sqrt(2) * (complex_y.real if m > 0 else complex_y.imag)


def test_real_sh_basis_matches_the_hand_written_bands_of_sh_basis():
    d = random_directions(1000)
    torch.testing.assert_close(real_sh_basis(d, [0, 1, 2, 3]), sh_basis(d, 3), rtol=0, atol=1e-14)


def test_real_sh_basis_keeps_the_order_of_the_degrees_given():
    d = random_directions(50)
    full = real_sh_basis(d, range(5))  # bands start at l^2
    torch.testing.assert_close(real_sh_basis(d, [4, 1]), torch.cat([full[:, 16:25], full[:, 1:4]], -1))


@pytest.mark.parametrize("ell", [0, 1, 2, 5, 8, 12, 16])
def test_real_sh_basis_matches_scipy(ell):
    d = random_directions(500)
    expected = np.stack([scipy_real_sh(d, ell, m) for m in range(-ell, ell + 1)], -1)
    np.testing.assert_allclose(real_sh_basis(d, [ell]).numpy(), expected, rtol=0, atol=1e-12)
    # float32 directions: the float64 truth at the same (rounded) directions, to 1e-4 absolute
    d32 = d.float()
    expected32 = np.stack([scipy_real_sh(d32, ell, m) for m in range(-ell, ell + 1)], -1)
    np.testing.assert_allclose(real_sh_basis(d32, [ell]).double().numpy(), expected32, rtol=0, atol=1e-4)


def test_real_sh_basis_is_orthonormal_up_to_degree_16():
    # Gauss-Legendre in z (24 nodes: exact for polynomials in z of degree <= 47) times a uniform grid of 40
    # azimuths (exact for trigonometric polynomials of degree < 40): Y_i Y_j up to l = 16 has degree <= 32 in
    # both once integrated over phi, so the quadrature is exact and the Gram matrix the identity.
    nodes, weights = np.polynomial.legendre.leggauss(24)
    n_phi = 40
    phi = 2 * np.pi * np.arange(n_phi) / n_phi
    z = torch.tensor(nodes)[:, None].expand(-1, n_phi)
    r = torch.sqrt(1 - z**2)
    phi_t = torch.tensor(phi)[None, :]
    d = torch.stack([r * torch.cos(phi_t), r * torch.sin(phi_t), z], -1).reshape(-1, 3)
    w = (torch.tensor(weights)[:, None] * (2 * np.pi / n_phi)).expand(-1, n_phi).reshape(-1)
    y = real_sh_basis(d, range(17))  # [P, 289]
    gram = (y * w[:, None]).T @ y
    torch.testing.assert_close(gram, torch.eye(289, dtype=torch.float64), rtol=0, atol=1e-12)


def test_ide_degrees_are_powers_of_two():
    assert ide_degrees(5) == [1, 2, 4, 8, 16]
    assert ide_degrees(1) == [1]


def test_ide_at_roughness_zero_is_the_plain_sh():
    d = random_directions(100)
    degrees = ide_degrees(5)
    torch.testing.assert_close(integrated_directional_encoding(d, torch.zeros(len(d), 1, dtype=d.dtype), degrees),
                               real_sh_basis(d, degrees), rtol=0, atol=0)


def vmf_expectation(mean, kappa, degrees, n_t=200, n_beta=64):
    """E[Y(omega)] for omega ~ vMF(mean, kappa) by quadrature in the frame of the mean: Gauss-Legendre in
    t = omega . mean on [1 - 60 / kappa, 1] (the density's e^{kappa (t - 1)} is e^{-60} beyond) and a uniform grid
    of angles beta around the mean (exact for the trigonometric polynomial of degree l in beta)."""
    nodes, weights = np.polynomial.legendre.leggauss(n_t)
    width = 60 / kappa
    t = torch.tensor(1 - width / 2 + width / 2 * nodes)[:, None]  # [T, 1]
    w_t = torch.tensor(weights * width / 2)[:, None]
    beta = torch.arange(n_beta, dtype=torch.float64)[None, :] * (2 * math.pi / n_beta)  # [1, B]
    u = torch.nn.functional.normalize(torch.linalg.cross(mean, torch.tensor([0.3, -0.5, 0.8], dtype=mean.dtype)),
                                      dim=-1)
    v = torch.linalg.cross(mean, u)
    s = torch.sqrt(1 - t**2)
    omega = t[..., None] * mean + s[..., None] * (torch.cos(beta)[..., None] * u + torch.sin(beta)[..., None] * v)
    density = kappa / (2 * math.pi * -math.expm1(-2 * kappa)) * torch.exp(kappa * (t - 1))  # per unit t and beta
    w = (w_t * density * (2 * math.pi / n_beta)).expand(-1, n_beta)
    return (real_sh_basis(omega.reshape(-1, 3), degrees) * w.reshape(-1, 1)).sum(0)


def test_ide_approximates_the_expected_sh_under_a_von_mises_fisher_lobe():
    kappa = 200.0
    degrees = [1, 2, 3, 4]
    mean = torch.nn.functional.normalize(torch.tensor([0.2, -0.7, 0.4], dtype=torch.float64), dim=-1)
    expected = vmf_expectation(mean, kappa, degrees)
    # The quadrature against the exact Funk-Hecke factor A_l = I_{l+1/2}(kappa) / I_{1/2}(kappa):
    exact = torch.tensor([scipy.special.ive(ell + 0.5, kappa) / scipy.special.ive(0.5, kappa)
                          for ell in degrees for _ in range(2 * ell + 1)], dtype=torch.float64)
    torch.testing.assert_close(expected, exact * real_sh_basis(mean, degrees), rtol=0, atol=1e-12)
    # Ref-NeRF's exp(-l (l + 1) / (2 kappa)) differs from A_l by O(l^4 / kappa^2): relative 1.2e-4 at l = 4,
    # kappa = 200 (1.25e-5 at l = 1), and |Y_4^m| <= sqrt(9 / 4 pi) = 0.85, so 1.1e-4 absolute at most.
    ide = integrated_directional_encoding(mean, torch.tensor([1 / kappa], dtype=torch.float64), degrees)
    torch.testing.assert_close(ide, expected, rtol=0, atol=1.2e-4)
    assert not torch.allclose(ide, expected, rtol=0, atol=1e-6)  # an approximation, not the exact factor


def test_ide_blurs_high_bands_more():
    d = random_directions(10)
    ide = integrated_directional_encoding(d, torch.full((len(d), 1), 0.1, dtype=d.dtype), [1, 16])
    sh = real_sh_basis(d, [1, 16])
    torch.testing.assert_close(ide[:, :3], sh[:, :3] * math.exp(-0.1))  # l (l + 1) / 2 = 1
    torch.testing.assert_close(ide[:, 3:], sh[:, 3:] * math.exp(-13.6))  # 16 * 17 / 2 * 0.1


def test_reflect_straight_on_comes_back():
    n = torch.tensor([0.0, 0.0, 1.0])
    torch.testing.assert_close(reflect(torch.tensor([0.0, 0.0, -1.0]), n), torch.tensor([0.0, 0.0, 1.0]))


def test_reflect_keeps_the_angle_and_the_length_and_is_an_involution():
    d = random_directions(200)[:-4]
    n = random_directions(200, seed=1)[:-4]
    r = reflect(d, n)
    torch.testing.assert_close(torch.linalg.vector_norm(r, dim=-1), torch.ones(len(d), dtype=d.dtype))
    # omega_r . n = omega_o . n (the angle with the normal), and omega_r's tangential part is omega_o's reversed
    torch.testing.assert_close((r * n).sum(-1), (-d * n).sum(-1))

    def tangential(v):
        return v - (v * n).sum(-1, keepdim=True) * n

    torch.testing.assert_close(tangential(r), -tangential(-d))
    torch.testing.assert_close(reflect(r, n), d)  # d -> d - 2 (d . n) n is a Householder reflection: H H = I


def test_reflect_at_grazing_incidence_passes_straight_on():
    # d along the surface: omega_r = -omega_o = d
    d = torch.tensor([1.0, 0.0, 0.0])
    torch.testing.assert_close(reflect(d, torch.tensor([0.0, 0.0, 1.0])), d)


def test_linear_to_srgb_against_the_standard():
    x = torch.tensor([0.0, 0.0031308, 0.18, 0.5, 1.0], dtype=torch.float64)
    # 12.92 * 0.0031308; 18% grey and 0.5 from 1.055 x^(1/2.4) - 0.055
    expected = torch.tensor([0.0, 0.040449936, 0.46135612950044164, 0.7353569830524495, 1.0], dtype=torch.float64)
    torch.testing.assert_close(linear_to_srgb(x), expected, rtol=0, atol=1e-7)
    # the two pieces meet at the knee (the standard's constants are rounded: they agree to 1e-8)
    above = 1.055 * 0.0031308 ** (1 / 2.4) - 0.055
    assert abs(above - 12.92 * 0.0031308) < 1e-7


def test_linear_to_srgb_has_a_finite_gradient_at_zero():
    x = torch.tensor([0.0, 1e-30, 0.5], requires_grad=True)
    linear_to_srgb(x).sum().backward()
    assert torch.isfinite(x.grad).all()
    assert x.grad[0] == pytest.approx(12.92)


def test_unit_is_finite_at_zero():
    x = torch.tensor([[0.0, 0.0, 0.0], [1e-30, 0.0, 0.0], [3.0, 4.0, 0.0]], requires_grad=True)
    u = _unit(x)
    torch.testing.assert_close(u[2], torch.tensor([0.6, 0.8, 0.0]))
    u.sum().backward()
    assert torch.isfinite(u).all() and torch.isfinite(x.grad).all()


@pytest.mark.parametrize(("h_shape", "d_shape"), [((64, 32), (64, 3)), ((4, 16, 32), (4, 1, 3))])
def test_reflection_head_shapes_ranges_and_gradients(h_shape, d_shape):
    torch.manual_seed(0)
    head = ReflectionViewDependence(32, hidden=16, n_levels=5)
    h = torch.randn(h_shape, requires_grad=True)
    d = torch.nn.functional.normalize(torch.randn(d_shape), dim=-1)
    rgb, normals = head(h, d)
    assert rgb.shape == (*h_shape[:-1], 3) and normals.shape == (*h_shape[:-1], 3)
    assert ((rgb >= 0) & (rgb <= 1)).all()
    torch.testing.assert_close(torch.linalg.vector_norm(normals, dim=-1), torch.ones(h_shape[:-1]))
    (rgb.sum() + normals.sum()).backward()
    assert torch.isfinite(h.grad).all()
    assert all(torch.isfinite(p.grad).all() for p in head.parameters())
    assert ReflectionViewDependence.uses_normals


def test_reflection_head_is_view_dependent_and_its_normals_are_not():
    torch.manual_seed(0)
    head = ReflectionViewDependence(8, hidden=16)
    h = torch.randn(32, 8)
    d = torch.nn.functional.normalize(torch.randn(32, 3), dim=-1)
    rgb, normals = head(h, d)
    assert not torch.allclose(rgb, head(h, -d)[0])
    torch.testing.assert_close(head(h, -d)[1], normals)  # the predicted normals depend on the position alone


def test_normal_penalties_by_hand():
    d = torch.tensor([0.0, 0.0, -1.0])  # looking down the z axis
    gradient = torch.tensor([0.0, 0.0, -2.0])  # density grows downwards: the normal is +z, towards the camera
    up = torch.tensor([0.0, 0.0, 1.0])
    penalties = normal_penalties(torch.stack([up, d, torch.tensor([1.0, 0.0, 0.0])]), gradient, d)
    # n' = n: 1 - 1 = 0, facing the camera: 0. n' = d: 1 - (-1) = 2, and max(0, 1)^2 = 1.
    # n' sideways: 1 - 0 = 1, and n' . d = 0: 0.
    torch.testing.assert_close(penalties, torch.tensor([[0.0, 0.0], [2.0, 1.0], [1.0, 0.0]]))


def test_normal_penalties_broadcast_one_direction_per_ray():
    predicted = torch.nn.functional.normalize(torch.randn(2, 5, 3), dim=-1)
    gradient = torch.randn(2, 5, 3)
    d = torch.nn.functional.normalize(torch.randn(2, 1, 3), dim=-1)
    penalties = normal_penalties(predicted, gradient, d)
    assert penalties.shape == (2, 5, 2)
    torch.testing.assert_close(penalties, normal_penalties(predicted, gradient, d.expand(-1, 5, -1)))
    assert ((penalties[..., 0] >= 0) & (penalties[..., 0] <= 2)).all() and (penalties[..., 1] >= 0).all()
