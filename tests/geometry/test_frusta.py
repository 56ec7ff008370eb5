"""Cameras' views as pyramids (``nerfexp.geometry.frusta``): the nearest and farthest points of a box that a
view holds, by hand and against a float64 brute force over dense rays."""

import math

import pytest
import torch

from nerfexp.geometry.cameras import look_at
from nerfexp.geometry.frusta import box_reach, in_view, view_planes
from nerfexp.geometry.lenses import Intrinsics, pixel_grid, pixel_rays

F64 = torch.float64
BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], dtype=F64)


def camera(eye, target=(0.0, 0.0, 0.0)) -> torch.Tensor:
    return look_at(torch.tensor(eye, dtype=F64), torch.tensor(target, dtype=F64), torch.tensor([0.0, 1.0, 0.0],
                                                                                                   dtype=F64))[None]


def reach(c2w, focal, side=100):
    return [float(v) for v in box_reach(c2w, view_planes(c2w, Intrinsics.pinhole(focal, side, side, (1,)), side, side),
                                        BOX)]


def test_by_hand_outside_inside_and_looking_away():
    # from (0, 0, 5) down -z, slopes up to 49.5 / 50 = 0.99: the face z = 1 at 4 straight ahead; the far face's
    # corners (+-1, +-1, -1) at slope 1/6 lie in view: sqrt(36 + 2)
    assert reach(camera((0.0, 0.0, 5.0)), 50.0) == pytest.approx([4.0, math.sqrt(38.0)])
    # a narrow view (slope 49.5 / 1000): nearest still straight ahead, farthest the far face at the view's corner
    slope = 49.5 / 1000
    assert reach(camera((0.0, 0.0, 5.0)), 1000.0) == pytest.approx([4.0, 6 * math.sqrt(1 + 2 * slope ** 2)])
    # inside the box at z = 0.5: nearest 0 (the camera itself), farthest the corners (+-1, +-1, -1)
    assert reach(camera((0.0, 0.0, 0.5), (0.0, 0.0, -1.0)), 50.0) == pytest.approx([0.0, math.sqrt(2 + 1.5 ** 2)])
    # looking away from the box: none of it in view
    assert reach(camera((0.0, 0.0, 5.0), (0.0, 0.0, 10.0)), 50.0) == [math.inf, -math.inf]


def test_the_nearest_point_on_the_views_edge():
    # from (0, 0, 5) looking along +x, a view of slope 1 (focal 49.5 over a 100-pixel side) holds the points with
    # x >= |z - 5|: in the box x <= 1 would need z >= 4 > 1, so none of it
    assert reach(camera((0.0, 0.0, 5.0), (4.0, 0.0, 5.0)), 49.5) == [math.inf, -math.inf]
    # from (-3, 0, 3) looking along +x: the view (slope 1) holds the box where x + 3 >= |z - 3|, i.e. z <= x + 6;
    # the box's nearest point to the camera is the edge (-1, y, 1) at distance sqrt(4 + 4) = sqrt(8), in view
    # (slope (3 - 1) / (3 - 1) = 1: on the view's edge)
    near, _ = reach(camera((-3.0, 0.0, 3.0), (0.0, 0.0, 3.0)), 49.5)
    assert near == pytest.approx(math.sqrt(8.0))


def brute_force(c2w, lens, side, box):
    """(min entry, max exit) over a dense grid of rays spanning the pixel centres' extent, slab test in float64."""
    grid = (torch.linspace(0.5, side - 0.5, 201, dtype=F64))
    pixels = torch.stack(torch.meshgrid(grid, grid, indexing="xy"), -1).reshape(-1, 2)
    d = pixel_rays(pixels, lens) @ c2w[0, :3, :3].T
    o = c2w[0, :3, 3]
    with torch.no_grad():
        inv = 1 / d
        t0, t1 = (box[0] - o) * inv, (box[1] - o) * inv
        entry = torch.minimum(t0, t1).amax(-1).clamp(min=0)
        exit_ = torch.maximum(t0, t1).amin(-1)
    hit = exit_ >= entry
    return float(entry[hit].min()), float(exit_[hit].max())


@pytest.mark.parametrize("seed", range(6))
def test_exact_bounds_hold_and_touch_a_dense_brute_force(seed):
    generator = torch.Generator().manual_seed(seed)
    eye = (torch.rand(3, generator=generator, dtype=F64) - 0.5) * 8
    target = (torch.rand(3, generator=generator, dtype=F64) - 0.5) * 1.5
    c2w = look_at(eye, target, torch.tensor([0.0, 0.0, 1.0], dtype=F64))[None]
    lens = Intrinsics.pinhole(60.0, 80, 80, (1,))
    near, far = box_reach(c2w, view_planes(c2w, lens, 80, 80), BOX)
    sampled_near, sampled_far = brute_force(c2w, lens[0], 80, BOX)
    # the exact bounds hold every sampled ray and the samples come within their spacing of them
    assert float(near) <= sampled_near + 1e-9 and float(far) >= sampled_far - 1e-9
    assert float(near) == pytest.approx(sampled_near, abs=0.05) and float(far) == pytest.approx(sampled_far, abs=0.05)


def test_a_distorted_views_pyramid_holds_every_pixel_ray():
    lens = Intrinsics(torch.tensor([[30.0, 28.0, 21.0, 17.0]], dtype=F64),
                      torch.tensor([[-0.2, 0.05, 0, 0, 0, 0, 0, 0]], dtype=F64), torch.tensor([False]))
    c2w = camera((0.0, 0.0, 5.0))
    planes = view_planes(c2w, lens, 36, 40)
    rays = pixel_rays(pixel_grid(36, 40, F64).reshape(-1, 2), lens[0]) @ c2w[0, :3, :3].T
    points = c2w[0, :3, 3] + 3 * rays
    assert in_view(points, c2w, planes).all()
    # and a point just outside the widest pixel ray is not in view
    assert not in_view(c2w[0, :3, 3] + 3 * torch.tensor([[10.0, 0.0, -1.0]], dtype=F64), c2w, planes).any()


def test_a_view_reaching_past_90_degrees_holds_everything():
    fisheye = Intrinsics(torch.tensor([[5.0, 5.0, 20.0, 20.0]], dtype=F64), torch.zeros(1, 8, dtype=F64),
                         torch.tensor([True]))
    c2w = camera((0.0, 0.0, 5.0))
    planes = view_planes(c2w, fisheye, 40, 40)  # theta up to 28 / 5 radians > 90 degrees: no pyramid
    assert (planes == 0).all()
    near, far = box_reach(c2w, planes, BOX)
    assert [float(near), float(far)] == pytest.approx([4.0, math.sqrt(36 + 2)])  # the whole box
