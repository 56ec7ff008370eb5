"""The Scene base class: the defaults a format may leave out, and where the occupancy grid's box comes from."""

import pytest
import torch

from nerfexp.data.base import Scene
from nerfexp.data.procedural import ProceduralScene, objects_box, scene_cameras
from nerfexp.data.views import Views
from nerfexp.errors import ConfigError
from nerfexp.geometry.boxes import frustum_aabb
from nerfexp.geometry.lenses import Intrinsics

NEAR, FAR = 2.0, 6.0


class BoxlessScene(Scene):
    """A format that knows no box of its own (as COLMAP's): the grid bounds it by the training cameras."""

    background, near, far = "white", NEAR, FAR

    def views(self, split: str) -> Views:
        raise AssertionError("the box is made from the views it is given")


def test_a_scene_that_leaves_the_optional_members_out_gets_their_defaults():
    scene = BoxlessScene()
    origins, directions = torch.rand(4, 3), torch.rand(4, 3)
    assert scene.model_rays(origins, directions) == (origins, directions)  # world rays, the same tensors
    assert scene.ray_bounds() == (NEAR, FAR) and scene.depth_bounds() is None
    assert scene.aabb is None and scene.bounding_box() is None


def test_the_box_comes_from_the_config_then_the_scene_then_the_cameras():
    box = objects_box()  # slab [-0.75, 0.75]^2 x [-0.7, -0.5], the rods reach z = 0.6
    torch.testing.assert_close(box, torch.tensor([[-0.75, -0.75, -0.7], [0.75, 0.75, 0.6]]))
    # the scene's own: Blender's [-1.5, 1.5]^3, the objects with at least 0.75 of room on every side
    scene_box = ProceduralScene(image_size=64).box(None, NEAR, FAR)
    assert scene_box.tolist() == [[-1.5] * 3, [1.5] * 3]
    assert (box[0] - scene_box[0] >= 0.75).all() and (scene_box[1] - box[1] >= 0.75).all()
    explicit = ProceduralScene(aabb=[[-1, -2, -3], [1, 2, 3]])
    assert explicit.box(None, NEAR, FAR).tolist() == [[-1, -2, -3], [1, 2, 3]]
    with pytest.raises(ConfigError, match="data.aabb: expected"):
        ProceduralScene(aabb=[[0, 0, 0], [1, -1, 1]]).box(None, NEAR, FAR)
    # the training views' own lenses bound it: each its own, principal points off the centre by up to 2 px
    lenses = Intrinsics.pinhole(10.0, 8, 8, (20,))
    lenses.params[:, 2] += torch.linspace(-2, 2, 20, dtype=torch.float64)
    views = Views(rgba=torch.zeros(20, 8, 8, 4), c2w=scene_cameras("train", 20).float(), intrinsics=lenses)
    box = BoxlessScene().box(views, NEAR, FAR)
    assert torch.equal(box, frustum_aabb(views.c2w, lenses, 8, 8, NEAR, FAR))
    assert not torch.equal(box, frustum_aabb(views.c2w, Intrinsics.pinhole(10.0, 8, 8, (20,)), 8, 8, NEAR, FAR))
    with pytest.raises(ConfigError, match="set data.aabb"):
        BoxlessScene().box(None, NEAR, FAR)
