"""The data module's checks before the first step: no training view among the validation or test views of any
scene, files or none (a rendered scene's views are compared by their pixels and poses), and the views each stage
scores."""

import pytest
import torch

from nerfexp.data.datamodule import RayDataModule
from nerfexp.data.procedural import ProceduralScene
from nerfexp.data.views import Views
from nerfexp.errors import DatasetError


class LeakyScene(ProceduralScene):
    """The built-in scene whose test split renders the first training cameras: test views training sees."""

    def views(self, split: str) -> Views:
        return super().views("train").subset(torch.tensor([2, 0])) if split == "test" else super().views(split)


SMALL = {"image_size": 12, "n_train": 4, "n_val": 1, "n_test": 2, "supersample": 1}


@pytest.mark.parametrize("pose_noise", [None, [2.0, 0.05]])
def test_a_rendered_scene_whose_test_views_are_training_views_is_refused(pose_noise):
    # with pose noise the training poses are perturbed; the check compares the poses the scene gave
    data = RayDataModule(LeakyScene(**SMALL), batch_rays=64, pose_noise=pose_noise)
    with pytest.raises(DatasetError) as caught:
        data.setup("fit")
    assert str(caught.value) == ("the test view 0 and the training view 2 are one view (they have the same pixels "
                                 "and the same pose): a score on views training saw is no test score; keep it in one "
                                 "split")


def test_the_built_in_scene_loads_and_each_stage_scores_its_splits():
    data = RayDataModule(ProceduralScene(**SMALL), batch_rays=64, pose_noise=[2.0, 0.05])
    data.setup("fit")
    assert {split: len(views) for split, views in data.scored_views("fit").items()} == {"val": 1, "test": 2}
    assert list(data.scored_views("test")) == ["test"]
    assert not torch.equal(data.train_views().c2w, data.true_train_poses)  # perturbed for training, checked as given
