"""Boxes: parsed from the config, and the box of what cameras see (``nerfexp.geometry.boxes``)."""

import pytest
import torch

from nerfexp.data.procedural import objects_box, scene_cameras
from nerfexp.errors import ConfigError
from nerfexp.geometry.boxes import frustum_aabb, parse_aabb
from nerfexp.geometry.lenses import Intrinsics, distortion_vector, pixel_rays

NEAR, FAR = 2.0, 6.0
N_CAMERAS = 20


def test_a_box_is_read_nested_or_flat_and_anything_else_names_the_key():
    assert parse_aabb([[-1, -2, -3], [1, 2, 3]]).tolist() == [[-1, -2, -3], [1, 2, 3]]
    assert parse_aabb([-1, -2, -3, 1, 2, 3]).tolist() == [[-1, -2, -3], [1, 2, 3]]
    for bad in ([1, 2, 3], [[0, 0, 0], [1, -1, 1]], "big", [[0, 0, 0], [1, 1, float("nan")]]):
        with pytest.raises(ConfigError, match="data.aabb: expected"):
            parse_aabb(bad)


def test_the_box_of_the_cameras_frusta_holds_everything_they_see():
    # cameras on a sphere of radius 4 looking at the origin, seeing from 2 to 6: the box of their frusta
    # reaches beyond the far side of the sphere (6 - 4 = 2 from the origin at least) and holds the objects
    box = objects_box()
    lenses = Intrinsics.pinhole(10.0, 8, 8, (N_CAMERAS,))
    frusta = frustum_aabb(scene_cameras("train", N_CAMERAS).float(), lenses, 8, 8, NEAR, FAR)
    assert (frusta[0] <= box[0]).all() and (frusta[1] >= box[1]).all() and (frusta[1] - frusta[0]).min() > 4


def dense_frustum_points(c2w, lenses, height, width, samples=201, depths=5):
    """Points [K, 3] float64 of the cameras' frusta: rays through a ``samples`` x ``samples`` grid over each
    image's whole extent (edges and corners included, far finer than the box's own samples), at ``depths``
    distances from NEAR to FAR."""
    u = torch.linspace(0, width, samples, dtype=torch.float64)
    v = torch.linspace(0, height, samples, dtype=torch.float64)
    pixels = torch.stack(torch.meshgrid(u, v, indexing="xy"), -1)  # [S, S, 2]
    d = pixel_rays(pixels, lenses.unsqueeze(2))  # [N, S, S, 3]
    world = torch.einsum("nij,nabj->nabi", c2w[:, :3, :3], d)
    origins = c2w[:, None, None, :3, 3]
    return torch.cat([origins + t * world for t in torch.linspace(NEAR, FAR, depths).tolist()]).reshape(-1, 3)


@pytest.mark.parametrize("lens", [
    Intrinsics.pinhole(10.0, 8, 8),
    # a barrel-distorted lens with unequal focal lengths and its principal point off the centre
    Intrinsics(torch.tensor([9.0, 11.0, 3.0, 5.0], dtype=torch.float64),
               distortion_vector({"k1": -0.2, "p1": 0.01}), torch.tensor(False)),
    # a fisheye wide enough that its image's corners bend far from a pinhole's
    Intrinsics(torch.tensor([4.0, 4.0, 4.0, 4.0], dtype=torch.float64),
               distortion_vector({"k1": 0.05}), torch.tensor(True)),
], ids=["pinhole", "opencv-off-centre", "fisheye"])
def test_every_point_of_every_frustum_lies_in_the_box_and_the_box_is_tight(lens):
    c2w = scene_cameras("train", N_CAMERAS)
    lenses = Intrinsics(*(x.expand(N_CAMERAS, *x.shape) for x in (lens.params, lens.distortion, lens.fisheye)))
    box = frustum_aabb(c2w.float(), lenses, 8, 8, NEAR, FAR).double()
    points = dense_frustum_points(c2w, lenses, 8, 8)
    assert (points >= box[0]).all() and (points <= box[1]).all()
    # the padding is far (1 - cos(h / 2)) for a sample spacing h of a few degrees: well under 1% of FAR
    assert (points.amin(0) - box[0]).max() < 0.01 * FAR and (box[1] - points.amax(0)).max() < 0.01 * FAR
