"""A trained run's scene built back: the refined training cameras in place of the scene's, every other member the
scene's own."""

from dataclasses import fields
from pathlib import Path

import pytest
import torch

from nerfexp.data.base import Scene
from nerfexp.data.procedural import ProceduralScene
from nerfexp.errors import NerfexpError
from nerfexp.products.trained import RefinedScene


def test_a_refined_scene_has_the_shared_members_of_the_scene_it_wraps():
    scene = ProceduralScene(image_size=8, n_train=3, n_val=1, background="black", near=1.5, far=5.0,
                            aabb=[[-1, -1, -1], [1, 1, 1]], density_noise_std=0.5)
    refined = RefinedScene(scene, torch.eye(4).expand(3, 4, 4), Path("cameras/train_poses.json"))
    members = {member.name: getattr(refined, member.name) for member in fields(Scene)}
    assert members == {"n_train": 3, "n_val": 1, "background": "black", "near": 1.5, "far": 5.0,
                       "aabb": [[-1, -1, -1], [1, 1, 1]], "density_noise_std": 0.5}
    assert refined.source() is None  # Scene's method, not shadowed by the poses file's path


def test_a_refined_scene_trains_on_the_refined_cameras_and_tests_on_the_scenes():
    scene = ProceduralScene(image_size=8, n_train=3, n_val=1, n_test=2, supersample=1)
    refined_c2w = scene.views("train").c2w.clone()
    refined_c2w[:, :3, 3] += 0.25  # every camera moved by (0.25, 0.25, 0.25)
    refined = RefinedScene(scene, refined_c2w, Path("cameras/train_poses.json"))
    assert torch.equal(refined.views("train").c2w, refined_c2w)
    assert torch.equal(refined.views("test").c2w, scene.views("test").c2w)
    assert refined.ray_bounds() == scene.ray_bounds() and torch.equal(refined.bounding_box(), scene.bounding_box())


def test_refined_cameras_of_another_count_are_refused_naming_their_file():
    scene = ProceduralScene(image_size=8, n_train=3, supersample=1)
    refined = RefinedScene(scene, torch.eye(4).expand(2, 4, 4), Path("run/cameras/train_poses.json"))
    with pytest.raises(NerfexpError, match=r"^run/cameras/train_poses.json holds 2 refined training cameras and the "
                                           r"scene has 3 training views"):
        refined.views("train")
