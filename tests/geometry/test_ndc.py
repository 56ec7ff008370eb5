"""NDC rays against the closed-form projection of points, and rendering rays of any direction length."""

import math

import pytest
import torch

from nerfexp.geometry.ndc import ndc_rays
from nerfexp.nerf.hierarchy import HierarchyChoice
from nerfexp.nerf.volume_renderer import VolumeRenderer
from tests.analytic import Slab

FOCAL, HEIGHT, WIDTH = 50.0, 30, 40


def project(points, near, focal=FOCAL, height=HEIGHT, width=WIDTH):
    """The paper's NDC map of points [..., 3], written out independently (float64)."""
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    return torch.stack([-focal / (width / 2) * x / z, -focal / (height / 2) * y / z, 1 + 2 * near / z], -1)


def random_rays(n=200, seed=0):
    """Rays starting near the origin, looking down -z within a cone (d_z <= -0.5), not unit length."""
    g = torch.Generator().manual_seed(seed)
    origins = 0.3 * torch.randn(n, 3, generator=g, dtype=torch.float64)
    directions = torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.4
    directions[:, 2] = -(0.5 + torch.rand(n, generator=g, dtype=torch.float64))
    return origins, directions * (0.5 + torch.rand(n, 1, generator=g, dtype=torch.float64))


@pytest.mark.parametrize("near", [1.0, 0.5, 2.0])
def test_points_on_a_ray_map_onto_its_ndc_ray_at_the_closed_form_t(near):
    # A point p on the ray projects to z' = 1 + 2 near / p_z; the NDC ray starts at z' = -1 with d'_z = 2,
    # so p must lie on it at t' = (z' + 1) / 2 = 1 + near / p_z: check o' + t' d' = pi(p) in all coordinates.
    origins, directions = random_rays()
    o_ndc, d_ndc = ndc_rays(origins, directions, FOCAL, HEIGHT, WIDTH, near)
    t_plane = (-near - origins[:, 2]) / directions[:, 2]  # where the ray crosses z = -near
    for extra in (0.0, 0.1, 1.0, 7.0, 100.0):
        points = origins + (t_plane + extra)[:, None] * directions
        t_ndc = 1 + near / points[:, 2]
        torch.testing.assert_close(o_ndc + t_ndc[:, None] * d_ndc, project(points, near), rtol=0, atol=1e-9)
    torch.testing.assert_close(o_ndc, project(origins + t_plane[:, None] * directions, near))


def test_near_plane_is_t_zero_and_infinity_is_t_one():
    origins, directions = random_rays()
    o_ndc, d_ndc = ndc_rays(origins, directions, FOCAL, HEIGHT, WIDTH, 1.0)
    assert torch.allclose(o_ndc[:, 2], torch.tensor(-1.0, dtype=torch.float64))
    assert torch.allclose(d_ndc[:, 2], torch.tensor(2.0, dtype=torch.float64))
    # At t' = 1 the ray reaches its vanishing point: pi(o + T d) as T -> inf is (-a dx/dz, -b dy/dz, 1).
    a, b = 2 * FOCAL / WIDTH, 2 * FOCAL / HEIGHT
    dx, dy, dz = directions.unbind(-1)
    vanishing = torch.stack([-a * dx / dz, -b * dy / dz, torch.ones_like(dz)], -1)
    torch.testing.assert_close(o_ndc + d_ndc, vanishing)
    far = origins + 1e10 * directions
    torch.testing.assert_close(project(far, 1.0), vanishing, rtol=0, atol=1e-8)


def test_image_edges_map_to_plus_minus_one_and_the_axis_to_the_centre():
    # From the origin, the ray through the right edge of the image (x / -z = (W/2) / f) ends at x' = 1,
    # the top edge at y' = 1, and the optical axis stays on x' = y' = 0 (the docstring's example).
    origins = torch.zeros(3, 3, dtype=torch.float64)
    directions = torch.tensor([[WIDTH / 2 / FOCAL, 0, -1], [0, HEIGHT / 2 / FOCAL, -1], [0, 0, -1]],
                              dtype=torch.float64)
    o_ndc, d_ndc = ndc_rays(origins, directions, FOCAL, HEIGHT, WIDTH, 1.0)
    torch.testing.assert_close(o_ndc + d_ndc, torch.tensor([[1.0, 0, 1], [0, 1, 1], [0, 0, 1]], dtype=torch.float64))
    assert o_ndc[2].tolist() == [0, 0, -1] and d_ndc[2].tolist() == [0, 0, 2]


def test_ndc_ray_does_not_depend_on_the_direction_length():
    origins, directions = random_rays()
    one = ndc_rays(origins, directions, FOCAL, HEIGHT, WIDTH, 1.0)
    three = ndc_rays(origins, 3 * directions, FOCAL, HEIGHT, WIDTH, 1.0)
    for a, b in zip(one, three):
        torch.testing.assert_close(a, b)
        assert torch.isfinite(a).all()


class RecordingSlab(Slab):
    """Density 3 where |z| < 0.5, colour (0.2, 0.4, 0.6); records the view directions it is given."""

    def __init__(self):
        super().__init__(colour=(0.2, 0.4, 0.6))
        self.seen = []

    def forward(self, positions, directions):
        self.seen.append(directions)
        return super().forward(positions, directions)


@pytest.mark.parametrize("hierarchical", [False, True])
def test_a_longer_direction_with_scaled_bounds_renders_the_same(hierarchical):
    # The ray o + t d, d = (0, 0, -1) from z = 4 for t in [2, 6], and the same points as o + t (2 d) for
    # t in [1, 3]: the slab is 1 long either way, so the opacity is 1 - exp(-3 * 1) in both, and the depth
    # (in units of t) halves. The renderer must integrate densities over distance t |d|, not t.
    exact = -math.expm1(-3.0)
    origins = torch.tensor([[0.0, 0.0, 4.0]], dtype=torch.float64)
    unit = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)
    renders = []
    for scale in (1.0, 2.0):
        renderer = VolumeRenderer(RecordingSlab, HierarchyChoice(hierarchical, n_coarse=64, n_fine=128, n_single=256),
                                  near=2.0 / scale, far=6.0 / scale)
        out = renderer(origins, scale * unit, deterministic=True)
        renders.append(out["fine" if hierarchical else "coarse"])
    (a, b) = renders
    assert abs(a["opacity"].item() - exact) < 0.03
    torch.testing.assert_close(b["opacity"], a["opacity"])
    torch.testing.assert_close(b["rgb"], a["rgb"])
    torch.testing.assert_close(b["depth"], a["depth"] / 2)


def test_the_field_sees_viewdirs_or_else_the_unit_directions():
    renderer = VolumeRenderer(RecordingSlab, HierarchyChoice(hierarchical=True, n_coarse=4, n_fine=4, n_single=8),
                              near=2.0, far=6.0)
    origins = torch.tensor([[0.0, 0.0, 4.0]])
    directions = torch.tensor([[0.0, 0.0, -2.0]])
    renderer(origins, directions, deterministic=True)
    for network in (renderer.coarse, renderer.fine):
        seen = network.seen[-1].reshape(-1, 3)  # one per sample (the renderer may flatten the samples)
        torch.testing.assert_close(seen, torch.tensor([[0.0, 0.0, -1.0]]).expand_as(seen))
    viewdirs = torch.nn.functional.normalize(torch.tensor([[0.3, 0.1, -1.0]]), dim=-1)
    renderer(origins, directions, deterministic=True, viewdirs=viewdirs)
    for network in (renderer.coarse, renderer.fine):
        seen = network.seen[-1].reshape(-1, 3)
        torch.testing.assert_close(seen, viewdirs.expand_as(seen))
