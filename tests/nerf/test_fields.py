import functools
import math

import pytest
import torch

from nerfexp.nerf.encodings import IdentityEncoding, PositionalEncoding
from nerfexp.nerf.fields import (
    MLPViewDependence,
    NeRFField,
    NoViewDependence,
    SphericalHarmonicsViewDependence,
    sh_basis,
)
from nerfexp.nerf.hashgrid import HashGridEncoding
from nerfexp.nerf.reflection import ReflectionViewDependence, normal_penalties
from nerfexp.nerf.volume_renderer import query_packed, query_thresholded


def paper_field(view_head=None):
    head = view_head or functools.partial(MLPViewDependence, direction_encoding=PositionalEncoding(4), hidden=128)
    return NeRFField(PositionalEncoding(10), head, depth=8, width=256, skips=(5,))


def test_paper_mlp_parameter_count_by_hand():
    # Trunk inputs: 63, then 256 x 4, then 256 + 63 (the skip), then 256 x 2; sigma 256 -> 1;
    # feature 256 -> 256; hidden 256 + 27 -> 128; rgb 128 -> 3.
    trunk = (63 * 256 + 256) + 4 * (256 * 256 + 256) + ((256 + 63) * 256 + 256) + 2 * (256 * 256 + 256)
    head = (256 * 256 + 256) + ((256 + 27) * 128 + 128) + (128 * 3 + 3)
    assert sum(p.numel() for p in paper_field().parameters()) == trunk + (256 + 1) + head


def test_density_depends_on_position_only_and_colour_on_direction(device):
    torch.manual_seed(0)
    field = paper_field().to(device)
    x = torch.randn(64, 3).to(device)
    d1 = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1).to(device)
    d2 = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1).to(device)
    (rgb1, sigma1, penalties), (rgb2, sigma2, _) = field(x, d1), field(x, d2)
    assert rgb1.shape == (64, 3) and sigma1.shape == (64,) and penalties is None  # the paper's head: no penalties
    assert torch.equal(sigma1, sigma2)
    assert not torch.allclose(rgb1, rgb2)
    assert ((rgb1 >= 0) & (rgb1 <= 1)).all() and (sigma1 >= 0).all()


@pytest.mark.parametrize("head", [NoViewDependence, functools.partial(SphericalHarmonicsViewDependence, degree=0)])
def test_view_independent_heads_ignore_the_direction(head):
    field = NeRFField(IdentityEncoding(), head, depth=3, width=32, skips=(2,))
    x = torch.randn(16, 3)
    d = torch.nn.functional.normalize(torch.randn(16, 3), dim=-1)
    torch.testing.assert_close(field(x, d)[0], field(x, -d)[0])


def test_spherical_harmonics_head_is_view_dependent():
    torch.manual_seed(0)
    field = NeRFField(IdentityEncoding(), functools.partial(SphericalHarmonicsViewDependence, degree=2), depth=2,
                      width=16, skips=())
    x = torch.randn(16, 3)
    d = torch.nn.functional.normalize(torch.randn(16, 3), dim=-1)
    assert not torch.allclose(field(x, d)[0], field(x, -d)[0])


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_basis_is_orthonormal_on_the_sphere(degree):
    # Integrate Y_i Y_j over the sphere with a Fibonacci lattice (equal-area points): 4 pi mean = delta_ij.
    n = 200_000
    k = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * k / n
    phi = torch.pi * (1 + 5 ** 0.5) * k
    r = torch.sqrt(1 - z * z)
    d = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)
    Y = sh_basis(d, degree)
    gram = 4 * torch.pi * (Y.T @ Y) / n
    torch.testing.assert_close(gram, torch.eye((degree + 1) ** 2, dtype=torch.float64), atol=1e-4, rtol=0)


def test_bad_field_config_is_named():
    with pytest.raises(ValueError, match="density_activation"):
        NeRFField(IdentityEncoding(), NoViewDependence, depth=2, width=8, skips=(), density_activation="exp")
    with pytest.raises(ValueError, match="skips"):
        NeRFField(IdentityEncoding(), NoViewDependence, depth=2, width=8, skips=(5,))


def test_truncated_exp_is_exp_finite_everywhere_with_bounded_gradient():
    from nerfexp.nerf.fields import TRUNC_EXP_GRADIENT_CLAMP, trunc_exp

    x = torch.tensor([-50.0, 0.0, 3.0, 14.0, 20.0, 88.0, 1e4], requires_grad=True)
    y = trunc_exp(x)
    torch.testing.assert_close(y[:6], torch.exp(x[:6].detach()))  # exp itself wherever float32 holds it
    assert torch.isfinite(y).all() and y[-1] > 1e38  # exp(1e4) clamped just below float32's largest value
    y.sum().backward()
    cap = math.exp(TRUNC_EXP_GRADIENT_CLAMP)
    torch.testing.assert_close(x.grad[:4], torch.exp(x[:4].detach()))  # the exact gradient below the clamp
    torch.testing.assert_close(x.grad[4:], torch.full((3,), cap))
    # the exact derivative where it is not truncated, by finite differences in float64
    assert torch.autograd.gradcheck(trunc_exp, torch.tensor([-3.0, 0.5, 9.0], dtype=torch.float64, requires_grad=True))


@pytest.mark.parametrize("activation", ["relu", "softplus", "trunc_exp"])
def test_density_activations_are_config_choices(activation):
    field = NeRFField(IdentityEncoding(), NoViewDependence, depth=2, width=16, skips=(), density_activation=activation)
    sigma = field(torch.randn(32, 3) * 100, torch.zeros(32, 3)).sigma
    assert torch.isfinite(sigma).all() and (sigma >= 0).all()
    with pytest.raises(ValueError, match="field.density_activation: expected one of .*'trunc_exp'.*got 'exp'"):
        NeRFField(IdentityEncoding(), NoViewDependence, depth=2, width=16, skips=(), density_activation="exp")


def reflection_field(dtype=torch.float64):
    torch.manual_seed(0)
    head = functools.partial(ReflectionViewDependence, hidden=16, n_levels=3, normal_weight=0.5, orientation_weight=2.0)
    return NeRFField(PositionalEncoding(2), head, depth=2, width=32, skips=(), density_activation="softplus").to(dtype)


def test_the_reflection_head_s_penalties_use_the_density_normals_taken_by_finite_differences():
    # The field's penalties are the weighted normal_penalties of the head's predicted normals against the
    # density's normals -d raw / dx; here that gradient comes from central differences of the density alone.
    field = reflection_field()
    x = torch.randn(20, 3, dtype=torch.float64)
    d = torch.nn.functional.normalize(torch.randn(20, 3, dtype=torch.float64), dim=-1)
    out = field(x, d)
    penalties, sigma = out.penalties, out.sigma
    assert penalties.shape == (20, 2) and field.penalty_names == ("normals", "orientation")

    def raw(points):  # the raw density: the activation inverted (softplus^-1 = log(expm1))
        return torch.log(torch.expm1(field.density(points)))

    h = 1e-6
    gradient = torch.stack([(raw(x + h * e) - raw(x - h * e)) / (2 * h) for e in torch.eye(3, dtype=x.dtype)], -1)
    _, predicted = field.view_head(field._trunk(x), d)
    expected = normal_penalties(predicted, gradient, d) * torch.tensor([0.5, 2.0], dtype=x.dtype)
    torch.testing.assert_close(penalties, expected.detach(), rtol=1e-6, atol=1e-8)
    torch.testing.assert_close(sigma, field.density(x))


def test_the_reflection_penalties_train_the_density_and_are_left_out_without_gradients():
    field = reflection_field(torch.float32)
    x, d = torch.randn(50, 3), torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    penalties = field(x, d).penalties
    penalties[:, 0].sum().backward()  # R_p: through the density's gradient (create_graph) and the predicted normals
    assert field.trunk[0].weight.grad.abs().sum() > 0 and field.view_head.normal.weight.grad.abs().sum() > 0
    assert all(torch.isfinite(p.grad).all() for p in field.parameters() if p.grad is not None)
    with torch.no_grad():  # rendering for evaluation: colour and density only, no second pass
        rgb, sigma, penalties = field(x, d)
    assert rgb.shape == (50, 3) and ((rgb >= 0) & (rgb <= 1)).all() and sigma.shape == (50,) and penalties is None


@pytest.mark.parametrize("threshold", [1e-30, 0.03])
def test_an_alpha_threshold_asks_the_colour_of_a_real_field_only_where_it_renders_and_changes_nothing_else(threshold):
    # A real field (the hash grid's NGP field): with a threshold below every alpha, the two-stage query equals the
    # one-stage one, values and gradients; with a threshold, the samples it keeps answer as before and the
    # others zeros, and the gradient reaches the tables only through the samples kept.
    torch.manual_seed(0)
    encoding = HashGridEncoding(n_levels=4, features_per_level=2, log2_table_size=10, coarsest=4, finest=32,
                                aabb=[[-1.0] * 3, [1.0] * 3])
    for table in encoding.parameters():  # a trained-looking field: densities that differ from place to place
        torch.nn.init.uniform_(table, -1.0, 1.0)
    field = NeRFField(encoding, lambda width: NoViewDependence(width), depth=1, width=16, skips=(),
                      density_activation="softplus", density_bias=-1.0)
    points = torch.rand(4, 20, 3) * 2 - 1
    viewdirs = torch.nn.functional.normalize(torch.randn(4, 3), dim=-1)
    keep = torch.rand(4, 20) < 0.7
    lengths = torch.full((4, 20), 0.1)
    plain = query_packed(field, points, viewdirs, keep)
    (plain.rgb.sum() + plain.sigma.sum()).backward()
    plain_grad = [p.grad.clone() for p in field.parameters()]
    field.zero_grad()
    thresholded, coloured = query_thresholded(field, points, viewdirs, keep, lengths, threshold)
    (thresholded.rgb.sum() + thresholded.sigma.sum()).backward()
    chosen = keep & (-torch.expm1(-plain.sigma.detach() * 0.1) >= threshold)
    assert coloured == chosen.sum() > 0
    torch.testing.assert_close(thresholded.sigma, torch.where(chosen, plain.sigma, 0))
    torch.testing.assert_close(thresholded.rgb, torch.where(chosen[..., None], plain.rgb, 0))
    if threshold < 1e-20:  # below every alpha: the same query
        assert chosen.equal(keep)
        for p, g in zip(field.parameters(), plain_grad, strict=True):
            torch.testing.assert_close(p.grad, g)
    else:
        assert 0 < chosen.sum() < keep.sum()
