"""Surfaces from sampled densities (``nerfexp.geometry.surfaces``): the grid's layout by hand, marching
cubes on a ball against the sphere, and points along rays."""

import numpy as np
import pytest
import torch

from nerfexp.geometry.surfaces import grid_points, grid_shape, grid_spacing, isosurface, ray_points

F64 = torch.float64


def test_the_grid_has_resolution_cells_on_the_longest_edge_and_near_cubes_on_the_others():
    box = torch.tensor([[0.0, 0.0, 0.0], [2.0, 1.0, 0.2]])
    assert grid_shape(box, 8) == (9, 5, 2)  # 8 cells of 0.25; 1 / 0.25 = 4; 0.2 / 0.25 = 0.8 -> 1
    assert grid_shape(box, 1) == (2, 2, 2)  # at least one cell on every edge
    torch.testing.assert_close(grid_spacing(box, (9, 5, 2)), torch.tensor([0.25, 0.25, 0.2], dtype=F64))


def test_grid_points_lie_at_lower_plus_index_times_spacing_in_flat_c_order():
    box = torch.tensor([[-1.0, 0.5, 2.0], [1.0, 1.5, 2.3]], dtype=F64)
    shape = (5, 3, 4)
    points = grid_points(box, shape, torch.arange(5 * 3 * 4)).reshape(*shape, 3)
    i, j, k = (torch.arange(n, dtype=F64) for n in shape)
    expected = torch.stack(torch.meshgrid(-1 + 0.5 * i, 0.5 + 0.5 * j, 2 + 0.1 * k, indexing="ij"), -1)
    torch.testing.assert_close(points, expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(points[-1, -1, -1], box[1].double(), rtol=0, atol=1e-6)  # the box, exactly spanned
    some = torch.tensor([0, 7, 59])  # any slice of indices gives its own points
    torch.testing.assert_close(grid_points(box, shape, some), points.reshape(-1, 3)[some])


def ball(box: torch.Tensor, resolution: int, values) -> tuple[np.ndarray, float]:
    """``values`` (distances from the centre [X, Y, Z] -> values) sampled on the grid over ``box``, and
    the largest spacing."""
    shape = grid_shape(box, resolution)
    points = grid_points(box, shape, torch.arange(int(np.prod(shape))))
    return values(points.norm(dim=-1)).reshape(shape).numpy(), grid_spacing(box, shape).max().item()


# an anisotropic box, so that a mistake in the spacing or the axes' order shows
BOX = torch.tensor([[-1.0, -0.8, -0.6], [1.0, 0.8, 0.7]])
RADIUS = 0.5


def test_the_isosurface_of_a_ball_lies_on_its_sphere_with_outward_normals_and_faces():
    # a smooth field, radius - distance, crosses 0 on the sphere: marching cubes' linear interpolation is
    # exact to O(h^2 / r) and the gradient is radial
    values, h = ball(BOX, 40, lambda r: RADIUS - r)
    mesh = isosurface(values, 0.0, BOX)
    distance = np.linalg.norm(mesh.vertices, axis=1)
    radial = mesh.vertices / distance[:, None]
    assert np.abs(distance - RADIUS).max() < h**2 / RADIUS
    assert np.allclose(np.linalg.norm(mesh.normals, axis=1), 1)
    assert (mesh.normals * radial).sum(1).min() > 0.99
    corners = mesh.vertices[mesh.faces]  # [F, 3, 3]
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    assert ((face_normals * corners.mean(1)).sum(1) > 0).all()  # counter-clockwise seen from outside


def test_the_isosurface_of_a_solid_ball_lies_within_half_a_cell_of_its_sphere():
    # 1 inside, 0 outside, level 1/2: each vertex half-way along a grid edge that the sphere crosses
    values, h = ball(BOX, 24, lambda r: (r < RADIUS).double())
    mesh = isosurface(values, 0.5, BOX)
    distance = np.linalg.norm(mesh.vertices, axis=1)
    assert np.abs(distance - RADIUS).max() <= h / 2 + 1e-9
    assert ((mesh.normals * mesh.vertices / distance[:, None]).sum(1) > 0).all()


@pytest.mark.parametrize("level", [-0.1, 1.0, 2.0])
def test_a_level_the_values_do_not_cross_is_a_value_error(level):
    values, _ = ball(BOX, 8, lambda r: (r < RADIUS).double())
    with pytest.raises(ValueError, match=f"no surface at level {level:g}: the values lie in \\[0, 1\\]"):
        isosurface(values, level, BOX)


def test_a_ray_ends_at_its_depth_along_its_direction():
    origins = torch.tensor([[0.0, 0.0, 4.0], [1.0, 2.0, 3.0]])
    directions = torch.tensor([[0.0, 0.0, -1.0], [0.6, 0.0, -0.8]])
    # 3 down from z = 4; 5 along (0.6, 0, -0.8) from (1, 2, 3): (1 + 3, 2, 3 - 4)
    expected = torch.tensor([[0.0, 0.0, 1.0], [4.0, 2.0, -1.0]])
    torch.testing.assert_close(ray_points(origins, directions, torch.tensor([3.0, 5.0])), expected)
