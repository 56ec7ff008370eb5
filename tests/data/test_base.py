"""The Scene base class: the members every format shares (held once, each format's defaults those of its config),
the defaults a format may leave out, and where the occupancy grid's box comes from."""

from dataclasses import dataclass, fields
from pathlib import Path

import pytest
import torch
from hydra.utils import get_class
from omegaconf import OmegaConf

from nerfexp.data.base import FolderScene, Scene
from nerfexp.data.procedural import ProceduralScene, objects_box, scene_cameras
from nerfexp.data.views import Views
from nerfexp.errors import ConfigError
from nerfexp.geometry.boxes import frustum_aabb
from nerfexp.geometry.lenses import Intrinsics

NEAR, FAR = 2.0, 6.0
CONF_DATA = Path(__file__).parents[2] / "conf" / "data"
FORMATS = sorted(path.stem for path in CONF_DATA.glob("*.yaml"))
# the members Scene's docstring names for every format, and FolderScene's for every format read from a folder
SHARED = {"n_train", "n_val", "background", "near", "far", "aabb", "density_noise_std"}
FOLDER = {"root", "scene", "catalog", "mirror", "max_side"}


@dataclass(kw_only=True)
class BoxlessScene(Scene):
    """A format that knows no box of its own (as COLMAP's): the grid bounds it by the training cameras."""

    near: float = NEAR  # a format declares a shared field again only to change its default
    far: float = FAR

    def views(self, split: str) -> Views:
        raise AssertionError("the box is made from the views it is given")


def test_a_scene_that_leaves_the_optional_members_out_gets_their_defaults():
    scene = BoxlessScene()
    origins, directions = torch.rand(4, 3), torch.rand(4, 3)
    assert scene.model_rays(origins, directions) == (origins, directions)  # world rays, the same tensors
    assert scene.ray_bounds() == (NEAR, FAR) and scene.depth_bounds() is None
    assert scene.aabb is None and scene.bounding_box() is None
    assert (scene.n_train, scene.n_val, scene.background, scene.density_noise_std) == (None, 2, "white", 0.0)


def test_the_shared_members_are_declared_once_on_scene_and_folder_scene():
    assert {member.name for member in fields(Scene)} == SHARED
    assert {member.name for member in fields(FolderScene)} == SHARED | FOLDER


@pytest.mark.parametrize("name", FORMATS)
def test_each_format_takes_the_shared_members_with_its_configs_values_as_defaults(name):
    config = OmegaConf.to_container(OmegaConf.load(CONF_DATA / f"{name}.yaml"))  # unresolved: ${scale.*} as text
    format_class = get_class(config.pop("_target_"))
    arguments = {member.name: member for member in fields(format_class) if member.init}
    shared = SHARED | (FOLDER if issubclass(format_class, FolderScene) else set())
    assert shared <= set(arguments)
    positional = [key for key, member in arguments.items() if not member.kw_only]
    assert positional == (["root"] if issubclass(format_class, FolderScene) else [])  # FORMAT(root), else keywords
    assert set(config) == set(arguments)  # a key of the config for every argument, and no other
    written = {key: value for key, value in config.items() if not str(value).startswith("${")}
    assert written == {key: arguments[key].default for key in written}



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
