"""Boxes: parsed from the config, and the box of what cameras see (``nerfexp.geometry.boxes``)."""

import pytest

from nerfexp.data.procedural import objects_box, scene_cameras
from nerfexp.errors import ConfigError
from nerfexp.geometry.boxes import frustum_aabb, parse_aabb

NEAR, FAR = 2.0, 6.0


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
    frusta = frustum_aabb(scene_cameras("train", 20).float(), 8, 8, 10.0, NEAR, FAR)
    assert (frusta[0] <= box[0]).all() and (frusta[1] >= box[1]).all() and (frusta[1] - frusta[0]).min() > 4
