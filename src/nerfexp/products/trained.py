"""A trained run's model built back from its files: ``load_module`` (the run's model with a checkpoint's
weights) and ``load_run`` (a run directory or checkpoint, its config with the user's changes checked, and its
model, ready to render). Its files are read as data below (``nerfexp.rundir.trained``: ``find_run``,
``run_config``, ``read_checkpoint``); what is built from them, the model and the scene's ray bounds, lives
here, above the training layer whose classes they are."""

from collections.abc import Callable
from dataclasses import fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig
from torch import Tensor

from nerfexp.data.base import Scene
from nerfexp.data.views import Views
from nerfexp.errors import NerfexpError
from nerfexp.memory import network_bytes, require_memory
from nerfexp.rundir.layout import REFINED_POSES
from nerfexp.rundir.trained import find_run, read_checkpoint, read_refined_poses, run_config
from nerfexp.settings.checks import check_run_settings

if TYPE_CHECKING:
    import lightning as L


def load_module(cfg: DictConfig, checkpoint: Path) -> "tuple[L.LightningModule, int]":
    """The run's model (``cfg.model``) with the weights of ``checkpoint`` (``read_checkpoint``), on the
    CPU, and the number of optimizer steps it had taken."""
    from nerfexp.data.datamodule import fill_ray_bounds  # it imports Lightning: only where a module is loaded

    fill_ray_bounds(cfg)  # a run's saved config holds null where the scene chose near and far
    module = instantiate(cfg.model)
    state = read_checkpoint(checkpoint)
    module.on_load_checkpoint(state)  # as Lightning before loading weights: what is sized by the data (camera_opt)
    check_weights(state["state_dict"], module, checkpoint)
    module.load_state_dict(state["state_dict"])
    return module, state["global_step"]


def check_weights(weights: dict[str, torch.Tensor], module: torch.nn.Module, checkpoint: Path) -> None:
    """A NerfexpError in one line where a checkpoint's ``weights`` (a state_dict) do not fit ``module``: the
    first parameter or buffer that one has and the other lacks, or whose shapes differ, with both shapes
    (where torch's ``load_state_dict`` would list every one, a line each)."""
    expected = module.state_dict()
    for name in [*expected, *(name for name in weights if name not in expected)]:
        if name not in weights or name not in expected:
            where = "the checkpoint" if name not in weights else "this run's model"
            raise NerfexpError(f"{checkpoint}: not a checkpoint of this run's model: {name} is missing from {where}")
        if weights[name].shape != expected[name].shape:
            raise NerfexpError(f"{checkpoint}: not a checkpoint of this run's model: {name} has shape "
                               f"{list(weights[name].shape)} there and {list(expected[name].shape)} in this run's "
                               "model (another network size?)")


class TrainedRun(NamedTuple):
    """A run read back for rendering (``load_run``)."""

    run_dir: Path
    checkpoint: Path
    cfg: DictConfig  # the run's saved config, with the caller's overrides
    module: "L.LightningModule"  # with the checkpoint's weights, in eval mode
    step: int  # optimizer steps the checkpoint had taken


def load_run(run: str | Path, overrides: list[str] = (), chunk: int | None = None,
             refuse: Callable[[Path, DictConfig], None] | None = None) -> TrainedRun:
    """The run at ``run`` (a run directory, or a checkpoint file in one) read as data (``find_run``,
    ``run_config`` with ``overrides``, ``load_module``): its module in eval mode on the GPU where there is
    one, rendering ``chunk`` rays at once (None: the run's ``model.chunk``). ``refuse(run_dir, saved
    config)``, where given, is called before the checkpoint is read, to raise for runs a command cannot use;
    the config with the overrides is then checked as ``nerfexp`` checks a new run's settings
    (``check_run_settings``: a ConfigError naming the key as the user set it), before the checkpoint is read."""
    run_dir, checkpoint = find_run(run)
    if refuse is not None:
        refuse(run_dir, run_config(run_dir))
    cfg = run_config(run_dir, overrides)
    check_run_settings(cfg)
    module, step = load_module(cfg, checkpoint)
    if chunk is not None:  # refused where it cannot fit, before any rendering
        samples, field = module.renderer.samples_per_ray, cfg.model.renderer.field
        require_memory(f"--chunk {chunk}", f"an evaluation of {chunk} rays x {samples} samples",
                       network_bytes(chunk, samples, field.width, field.depth, training=False))
        module.chunk = chunk
    module.to("cuda" if torch.cuda.is_available() else "cpu").eval()
    return TrainedRun(run_dir, checkpoint, cfg, module, step)


class RefinedScene(Scene):
    """A trained run's scene whose training cameras are those its camera refinement left (``train_c2w`` [N, 4,
    4], from ``RUN_DIR/cameras/train_poses.json``): every other split and member is ``scene``'s. What is made
    from the training cameras (a render's orbit or spiral, the viewer's frustums, a box from their frusta)
    then follows the cameras the run learned the scene with."""

    def __init__(self, scene: Scene, train_c2w: Tensor, poses_file: Path):
        super().__init__(**{member.name: getattr(scene, member.name) for member in fields(Scene)})
        self.scene = scene
        self.train_c2w = train_c2w
        self.poses_file = poses_file

    def views(self, split: str) -> Views:
        views = self.scene.views(split)
        if split != "train":
            return views
        if len(views) != len(self.train_c2w):
            raise NerfexpError(f"{self.poses_file} holds {len(self.train_c2w)} refined training cameras and the scene "
                               f"has {len(views)} training views: not this scene's (another data.n_train?)")
        return replace(views, c2w=self.train_c2w.to(views.c2w.dtype))

    def split_rule(self) -> str | None:
        return self.scene.split_rule()

    def bounding_box(self) -> Tensor | None:
        return self.scene.bounding_box()

    def ray_bounds(self) -> tuple[float, float]:
        return self.scene.ray_bounds()

    def depth_bounds(self) -> Tensor | None:
        return self.scene.depth_bounds()

    def model_rays(self, origins: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        return self.scene.model_rays(origins, directions)


def run_scene(run_dir: Path, cfg: DictConfig) -> Scene:
    """The scene of the run in ``run_dir`` (its config ``cfg``'s ``data``), with the training cameras its camera
    refinement left where it refined them (``RefinedScene``), else as the data gives them."""
    scene = instantiate(cfg.data)
    refined = read_refined_poses(run_dir)
    return scene if refined is None else RefinedScene(scene, refined, Path(run_dir) / REFINED_POSES)
