"""Rays for Lightning: a scene's splits served as random training batches and whole evaluation images.

The datasets (``nerfexp.data.rays``) serve world rays; the loaders' collate step (``model_batch``) turns
them into the model's rays (NDC for forward-facing LLFF scenes) and adds the world view directions as
"viewdirs".
"""

import functools
import logging
from dataclasses import replace

import lightning as L
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, open_dict
from torch import Tensor
from torch.utils.data import DataLoader

from nerfexp.data.base import Scene
from nerfexp.data.pose_noise import check_pose_noise, perturbed_poses
from nerfexp.data.rays import RandomRays, WholeImages, model_batch
from nerfexp.data.views import Views, check_distinct_views
from nerfexp.nerf.backgrounds import BACKGROUNDS

log = logging.getLogger(__name__)
SPLITS = ("train", "val", "test")
SCORED = {"fit": ("val", "test"), "test": ("test",)}  # the splits that training and a test alone score


def fill_ray_bounds(cfg: DictConfig) -> str | None:
    """Set ``data.near`` and ``data.far`` left null in ``cfg`` (``data=colmap``: they come from the sparse
    points) to the scene's ``ray_bounds()``, in place, so that the renderer built from ``cfg`` and the
    config a run records hold the values used, and log one line saying where they came from. Values set in
    the config stay. Returns the scene's ``bounds_rule()`` (None where both were set)."""
    if cfg.data.get("near") is not None and cfg.data.get("far") is not None:
        return None
    scene = instantiate(cfg.data)
    near, far = scene.ray_bounds()
    rule = scene.bounds_rule()
    log.info("ray bounds near %.4g, far %.4g: %s", near, far, rule or "data.near and data.far")
    with open_dict(cfg.data):
        cfg.data.near, cfg.data.far = float(near), float(far)
    return rule


class RayDataModule(L.LightningDataModule):
    """Loads a scene's splits and serves them as rays: training batches of ``batch_rays`` rays in all
    (the global batch, split over the processes of a distributed run), whole images for evaluation
    (Lightning gives each process every world_size-th image, see
    ``nerfexp.training.recorders.gather_evaluations``). ``pose_noise`` [degrees, fraction]: the training
    views' poses perturbed by those known amounts (``nerfexp.data.pose_noise``), to measure camera refinement;
    None: as the scene gives them."""

    def __init__(self, scene: Scene, batch_rays: int, seed: int = 0, pose_noise: list | None = None):
        super().__init__()
        self.scene, self.batch_rays, self.seed = scene, batch_rays, seed
        self.pose_noise = check_pose_noise(pose_noise)  # (degrees, fraction of the cameras' radius) or None
        self.true_train_poses: Tensor | None = None  # c2w [N, 4, 4] of the training views, where perturbed
        self.background = torch.tensor(BACKGROUNDS[scene.background])
        self.splits: dict[str, Views] = {}
        self.split_check: dict | None = None  # what ``check_distinct_views`` checked, once ``setup("fit")`` ran
        self._collate = functools.partial(model_batch, scene)  # each loader's items -> the model's batches

    def _views(self, split: str) -> Views:
        if split not in self.splits:
            self.splits[split] = self.scene.views(split)
            if split == "train" and self.pose_noise is not None:
                self.splits[split] = self._perturbed(self.splits[split])
        return self.splits[split]

    def _perturbed(self, views: Views) -> Views:
        """``views`` with their poses perturbed by ``pose_noise`` (``nerfexp.data.pose_noise``, seeded with the
        run's seed); the true poses kept as ``true_train_poses``."""
        self.true_train_poses = views.c2w
        return replace(views, c2w=perturbed_poses(views.c2w, *self.pose_noise, self.seed))

    def train_views(self) -> Views:
        """The training views as training sees them (their poses perturbed where ``pose_noise`` says)."""
        return self._views("train")

    def setup(self, stage: str) -> None:
        """Before training, every split is loaded (and checked, as each format's loader checks it), so that
        bad data anywhere (a NaN pose in the test split, a missing image) stops a run before its first
        step rather than after it; then the splits are checked to share no view that they may not
        (``check_distinct_views``: no training view, nor a near copy of one, among the validation or test views,
        no view twice in a split), the training views with the poses the scene gave; what was checked is kept as
        ``split_check`` (results.json records it)."""
        if stage == "fit":
            given = {split: self._views(split) for split in SPLITS}
            if self.true_train_poses is not None:
                given["train"] = replace(given["train"], c2w=self.true_train_poses)
            self.split_check = check_distinct_views(given, self.background)

    def scored_views(self, stage: str) -> dict[str, Views]:
        """The views that ``stage`` ("fit": training, then its test; "test": a test alone) scores, by split
        (``SCORED``)."""
        return {split: self._views(split) for split in SCORED[stage]}

    def train_dataloader(self) -> DataLoader:
        trainer = self.trainer
        rank, world_size, step = ((trainer.global_rank, trainer.world_size, trainer.global_step)
                                  if trainer is not None else (0, 1, 0))
        # each process its part of the global batch; a resumed run's loader is made after the checkpoint
        # restored the step
        rays = RandomRays(self._views("train"), self.background, self.batch_rays, self.seed, start=step,
                          rank=rank, world_size=world_size)
        return DataLoader(rays, batch_size=None, collate_fn=self._collate)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(WholeImages(self._views("val"), self.background), batch_size=None,
                          collate_fn=self._collate)

    def test_dataloader(self) -> DataLoader:
        return DataLoader(WholeImages(self._views("test"), self.background), batch_size=None,
                          collate_fn=self._collate)

    def camera_centres(self) -> Tensor:
        """The training cameras' centres [N, 3] in world units (a contraction's inner region is fit to them)."""
        return self._views("train").c2w[:, :3, 3]

    def scene_box(self, near: float, far: float) -> Tensor:
        """The occupancy grid's box [2, 3] for this scene (``Scene.box``), from the training views where
        they are loaded already and the scene has no box of its own."""
        return self.scene.box(self.splits.get("train"), near, far)
