"""A trained run's model built back from its files: ``load_module`` (the run's model with a checkpoint's
weights) and ``load_run`` (a run directory or checkpoint, its config with the user's changes checked, and its
model, ready to render). Its files are read as data below (``nerfexp.rundir.trained``: ``find_run``,
``run_config``, ``read_checkpoint``); what is built from them, the model and the scene's ray bounds, lives
here, above the training layer whose classes they are."""

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig

from nerfexp.errors import NerfexpError
from nerfexp.memory import network_bytes, require_memory
from nerfexp.rundir.trained import find_run, read_checkpoint, run_config
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
