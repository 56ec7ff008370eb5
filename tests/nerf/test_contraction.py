"""Scene contraction and disparity spacing (``contraction=mipnerf360``) against float64 closed forms: the map and
its Jacobian on both sides of the unit sphere (continuous, with a continuous first derivative), extreme distances
finite, the world lengths a contracted cell spans, where rays leave the inner region, the spacing and its inverse,
and a renderer that integrates densities over world distances whatever the spacing."""

import math

import pytest
import torch

from nerfexp.nerf.contraction import SceneContraction, contract, stretch
from nerfexp.nerf.fields import FieldOutputs
from nerfexp.nerf.hierarchy import HierarchyChoice
from nerfexp.nerf.occupancy import OccupancyGrid, density_threshold
from nerfexp.nerf.samplers import Rays, first_samples, resample
from nerfexp.nerf.sampling import disparity_fraction, disparity_spaced, linear_share
from nerfexp.nerf.volume_renderer import VolumeRenderer

NORMS = ("l2", "linf")


def norm_of(x: torch.Tensor, norm: str) -> torch.Tensor:
    return torch.linalg.vector_norm(x, ord=2 if norm == "l2" else math.inf, dim=-1)


def outer_jacobian(x: torch.Tensor, norm: str) -> torch.Tensor:
    """The closed-form Jacobian [3, 3] of (2 - 1/r) x / r = (2/r - 1/r^2) x at x [3] with r = |x| > 1: the scalar
    times the identity plus x times the gradient of the scalar, d(2/r - 1/r^2)/dr = -2/r^2 + 2/r^3, and dr/dx
    = x / r (l2) or sign(x_k) e_k at the largest coordinate k (linf)."""
    r = norm_of(x, norm)
    if norm == "l2":
        grad_r = x / r
    else:
        k = int(x.abs().argmax())
        grad_r = torch.zeros_like(x)
        grad_r[k] = torch.sign(x[k])
    return (2 / r - 1 / r**2) * torch.eye(3, dtype=x.dtype) + torch.outer(x, (-2 / r**2 + 2 / r**3) * grad_r)


@pytest.mark.parametrize("norm", NORMS)
def test_contraction_is_the_closed_form_and_its_jacobian_too(norm):
    generator = torch.Generator().manual_seed(0)
    directions = torch.randn(50, 3, generator=generator, dtype=torch.float64)
    directions = directions / norm_of(directions, norm)[:, None]
    for radius in (0.3, 1 - 1e-9, 1 + 1e-9, 1.5, 10.0, 1e6):
        x = directions * radius
        expected = x if radius <= 1 else (2 - 1 / radius) * x / radius
        torch.testing.assert_close(contract(x, norm), expected, rtol=1e-12, atol=1e-12)
        for point in x[:10]:
            jacobian = torch.autograd.functional.jacobian(lambda p: contract(p, norm), point)
            truth = torch.eye(3, dtype=torch.float64) if radius <= 1 else outer_jacobian(point, norm)
            torch.testing.assert_close(jacobian, truth, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("norm", NORMS)
def test_contraction_and_its_jacobian_are_continuous_at_the_unit_sphere(norm):
    # on the sphere the outer branch's Jacobian is (2 - 1) I + (-2 + 2) x grad r^T = I, the inner branch's
    generator = torch.Generator().manual_seed(1)
    points = torch.randn(20, 3, generator=generator, dtype=torch.float64)
    points = points / norm_of(points, norm)[:, None]
    for delta in (1e-3, 1e-6):
        inside, outside = points * (1 - delta), points * (1 + delta)
        # the value: |c(outside) - c(inside)| is about 2 delta, the step between the two points
        gap = norm_of(contract(outside, norm) - contract(inside, norm), norm)
        assert (gap <= 2 * delta * (1 + 1e-6)).all(), gap
        for point in outside:
            jacobian = torch.autograd.functional.jacobian(lambda p: contract(p, norm), point)
            # the Jacobian moves away from I at a rate of order delta: it is continuous, not just bounded
            assert (jacobian - torch.eye(3, dtype=torch.float64)).abs().max() < 4 * delta


@pytest.mark.parametrize("norm", NORMS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_extreme_distances_contract_to_finite_points_on_or_inside_the_shell(norm, dtype):
    big = [1e6, 1e30, math.inf, -math.inf]
    x = torch.tensor([[b, 0, 0] for b in big] + [[b, b, 1] for b in big] + [[math.inf, -math.inf, 3.0],
                                                                          [1e30, 1e-30, 0], [0, 0, 0]], dtype=dtype)
    x.requires_grad_()
    c = contract(x, norm)
    assert torch.isfinite(c).all(), c
    lengths = norm_of(c, norm)
    assert (lengths <= 2).all(), lengths
    infinite = torch.isinf(x).any(-1)
    torch.testing.assert_close(lengths[infinite], torch.full_like(lengths[infinite], 2.0))  # inf: on the shell
    # the direction of an infinite point is that of its infinite coordinates; 1e6 lies 1e-6 inside the shell
    torch.testing.assert_close(c[2].detach(), torch.tensor([2.0, 0, 0], dtype=dtype))
    torch.testing.assert_close(c[0].detach(), torch.tensor([2 - 1e-6, 0, 0], dtype=dtype))
    c.sum().backward()
    assert torch.isfinite(x.grad).all(), x.grad


def test_the_stretch_is_the_inverse_maps_largest_derivative():
    # the inverse of the l2 contraction along a ray: r = 1 / (2 - rho) for rho = |c| > 1; its radial derivative
    # dr/drho = r^2, its tangential one r / rho: the largest is the radial one
    for rho in (0.5, 1.0, 1.2, 1.9, 1.999):
        c = torch.tensor([rho, 0.0, 0.0], dtype=torch.float64)
        r = 1 / (2 - rho) if rho > 1 else rho
        h = 1e-7
        radial = ((1 / (2 - (rho + h)) - 1 / (2 - (rho - h))) / (2 * h)) if rho > 1 else 1.0
        assert stretch(c).item() == pytest.approx(radial, rel=1e-5)
        assert stretch(c).item() >= (r / rho if rho > 1 else 1.0)
    assert stretch(torch.tensor([2.0, 0, 0])).item() == math.inf  # the shell: infinitely stretched


@pytest.mark.parametrize("norm", NORMS)
def test_rays_leave_the_inner_region_where_it_ends(norm):
    contraction = SceneContraction(norm, centre=[1.0, -2.0, 0.5], radius=3.0)
    generator = torch.Generator().manual_seed(2)
    origins = (torch.rand(100, 3, generator=generator, dtype=torch.float64) - 0.5) * 3 + torch.tensor([1.0, -2, 0.5])
    directions = torch.randn(100, 3, generator=generator, dtype=torch.float64) * 2  # not unit
    t = contraction.ray_split(origins, directions)
    exits = contraction.inner(origins + t[:, None] * directions)
    torch.testing.assert_close(norm_of(exits, norm), torch.ones(100, dtype=torch.float64))
    outside = torch.tensor([[10.0, -2, 0.5]], dtype=torch.float64)  # 3 radii away: starts outside
    assert contraction.ray_split(outside, torch.tensor([[1.0, 0, 0]], dtype=torch.float64)).item() == 0


def test_disparity_spacing_is_linear_then_even_in_disparity_and_its_inverse_undoes_it():
    s = torch.linspace(0, 1, 9, dtype=torch.float64).expand(4, 9)
    near = torch.tensor([0.1, 0.5, 0.0, 1.0], dtype=torch.float64)
    split = torch.tensor([2.0, 0.2, 5.0, 4.0], dtype=torch.float64)  # inside; starts outside; beyond far; inside
    far = torch.tensor([1e3, 1e3, 3.0, 1e30], dtype=torch.float64)
    t = disparity_spaced(s, near, split, far)
    assert linear_share(near, split, far).tolist() == [0.5, 0.0, 1.0, 0.5]
    torch.testing.assert_close(t[:, 0], near)
    torch.testing.assert_close(t[:, -1], far)
    assert (t.diff(dim=-1) > 0).all()
    # first ray: 5 samples evenly from 0.1 to 2, then 4 more evenly in disparity from 1/2 to 1/1000
    torch.testing.assert_close(t[0, :5], torch.linspace(0.1, 2.0, 5, dtype=torch.float64))
    torch.testing.assert_close(1 / t[0, 4:], torch.linspace(1 / 2, 1 / 1000, 5, dtype=torch.float64))
    torch.testing.assert_close(1 / t[1], torch.linspace(1 / 0.5, 1 / 1000, 9, dtype=torch.float64))  # all disparity
    torch.testing.assert_close(t[2], torch.linspace(0.0, 3.0, 9, dtype=torch.float64))  # all linear
    torch.testing.assert_close(disparity_fraction(t, near, split, far), s, rtol=0, atol=1e-12)


def constant_field(sigma: float):
    """A field of density ``sigma`` and colour (0.2, 0.4, 0.6) everywhere."""
    def field(positions, directions):
        shape = positions.shape[:-1]
        rgb = torch.tensor([0.2, 0.4, 0.6], dtype=positions.dtype).expand(*shape, 3)
        return FieldOutputs(rgb=rgb, sigma=torch.full(shape, sigma, dtype=positions.dtype))
    field.density = lambda positions: torch.full(positions.shape[:-1], sigma, dtype=positions.dtype)
    return field


class Constant(torch.nn.Module):
    def __init__(self, sigma: float):
        super().__init__()
        self.field = constant_field(sigma)
        self.density = self.field.density

    def forward(self, positions, directions):
        return self.field(positions, directions)


@pytest.mark.parametrize("hierarchical", [True, False])
def test_a_contracted_renderer_integrates_density_over_world_distances(hierarchical):
    # a constant density sigma on rays from the first sample t_0 to far absorbs 1 - exp(-sigma (far - t_0) |d|) of
    # the light, however the samples are spaced: the quadrature is exact for a constant, if intervals are world
    # lengths
    sigma, near, far = 0.01, 0.5, 300.0
    contraction = SceneContraction("l2", centre=[0.0, 0, 0], radius=2.0, far=far / 2)  # far in radii
    renderer = VolumeRenderer(lambda: Constant(sigma),
                              HierarchyChoice(hierarchical, n_coarse=16, n_fine=32, n_single=48), near=near, far=6.0,
                              contraction=contraction).double()  # the scene's far: not read
    assert renderer.ray_far == far
    origins = torch.tensor([[0.0, 0, 0], [1.0, 0.5, 0]], dtype=torch.float64)
    directions = torch.tensor([[0.0, 0, 1], [0.0, 2, 0]], dtype=torch.float64)  # the second of length 2
    out = renderer(origins, directions, deterministic=True)
    lengths = torch.tensor([1.0, 2.0], dtype=torch.float64)
    for name in out:
        opacity = 1 - torch.exp(-sigma * (far - out[name]["t_starts"][:, 0]) * lengths)
        torch.testing.assert_close(out[name]["opacity"], opacity, rtol=1e-10, atol=1e-12)
    split = contraction.ray_split(origins, directions)  # the first samples: half before it, half beyond
    assert ((out["coarse"]["t_starts"] <= split[:, None]).sum(-1) == out["coarse"]["t_starts"].shape[1] // 2).all()


def test_samples_beyond_the_split_are_even_in_disparity_and_resampling_keeps_them_in_range():
    near, far = torch.tensor([0.5, 0.5]), torch.tensor([100.0, 100.0])
    rays = Rays(torch.zeros(2, 3), torch.ones(2, 3), torch.ones(2, 3), near, far, split=torch.tensor([2.0, 2.0]))
    t = first_samples(rays, 8, deterministic=True)
    torch.testing.assert_close(t[:, :4], torch.tensor([0.6875, 1.0625, 1.4375, 1.8125]).expand(2, 4))
    torch.testing.assert_close((1 / t[:, 4:]).diff(dim=-1), (1 / t[:, 4:]).diff(dim=-1)[:, :1].expand(2, 3))
    weights = torch.zeros(2, 8)
    weights[:, 6] = 1.0  # all the mass in one far interval
    fine = resample(rays, t, weights, 16, deterministic=True)
    assert ((fine >= t[:, 5:6]) & (fine <= far[:, None])).all()  # the dilated interval 5..7 and no further


def test_a_contracted_grids_outer_cells_are_occupied_at_lower_densities():
    grid = OccupancyGrid(resolution=8, aabb=[[-2.0, -2, -2], [2.0, 2, 2]])
    uniform = grid.cell_thresholds()
    grid.world_scale = SceneContraction("l2", centre=[0.0, 0, 0], radius=1.0).stretch
    thresholds = grid.cell_thresholds()
    centres = grid.aabb[0] + (torch.stack(torch.meshgrid(*[torch.arange(8.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
                              + 0.5) * grid.cell_size
    inner = torch.linalg.vector_norm(centres, dim=-1) < 0.5
    assert torch.allclose(thresholds[inner], torch.tensor(uniform))  # unstretched inside the unit ball
    assert uniform == pytest.approx(density_threshold(grid.threshold, float(torch.linalg.vector_norm(grid.cell_size))))
    corner = torch.linalg.vector_norm(centres, dim=-1).argmax()
    assert thresholds[corner] == 0  # reaches the shell: infinitely long, occupied at any density
    assert (thresholds <= uniform).all()
