"""What every run leaves in its output directory, each file written atomically.

- ``status.json``: ``running`` (with host and process id), ``finished`` or ``failed`` (with the error),
  and the run's command-line overrides, so a report can list jobs that crashed or still run.
- ``metrics.jsonl``: one JSON object per evaluation: step, wall_time_s, split, psnr, ssim (means).
- ``results.json``: final test means, last validation PSNR, training time, throughput, parameters,
  the machine, the resolved choices and overrides.
- ``test/``: rendered test views (``r_{i}.png``) and their depth (``r_{i}_depth.png``).
- TensorBoard: rendered images beside the ground truth, and depth (through the run's logger); the
  run's choices and overrides as hyper-parameters, with the PSNR/SSIM scalars as their metrics.
- ``eval.json``: a checkpoint's scores on the test split (``nerfexp-eval``, ``EvalRecorder``).

A finished (or interrupted) run is read back by ``find_run``, ``run_config`` and ``load_module``: its
directory holds the config it ran with (``RUN_CONFIG``) and its checkpoints (``LAST_CHECKPOINT``).

In a distributed run (``trainer=ddp``) each process evaluates its share of the images; the recorders
gather every image's scores and renders to all processes (``gather_evaluations``), and only global
rank 0 writes files and logs, so the numbers are those of one process scoring every image.
"""

import json
import os
import pickle
import socket
import time
from pathlib import Path

import imageio.v3 as iio
import lightning as L
import numpy as np
import torch
from hydra.utils import instantiate
from lightning.pytorch.loggers import TensorBoardLogger
from lightning.pytorch.utilities.rank_zero import rank_zero_only
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException
from torch import Tensor
from torch.utils.tensorboard.summary import hparams as hparams_summaries

from nerfexp.data.datamodule import fill_ray_bounds
from nerfexp.errors import ConfigError, NerfexpError
from nerfexp.files import atomic_write
from nerfexp.metrics import quantize

STATUS = "status.json"
RESULTS = "results.json"
EVAL = "eval.json"
RUN_CONFIG = Path(".hydra", "config.yaml")  # the composed config, as Hydra saves it in every run directory
LAST_CHECKPOINT = Path("checkpoints", "last.ckpt")
HPARAM_METRICS = ("val/psnr", "val/ssim", "test/psnr", "test/ssim")  # the HPARAMS view's metric columns


def is_global_zero() -> bool:
    """Whether this process is global rank 0, the one that writes a run's files: always in a run of one
    process; known before any trainer exists from the environment a launcher sets (``RANK``,
    ``LOCAL_RANK``, ``SLURM_PROCID``), and kept up to date by Lightning's strategies."""
    return rank_zero_only.rank == 0


def write_status(output_dir: str | Path, state: str, overrides: list[str], **details) -> None:
    """Record a run's ``state`` (running, finished, failed) with its host, process id and ``details``."""
    record = {"state": state, "overrides": list(overrides), "host": socket.gethostname(), "pid": os.getpid(),
              "time_unix": time.time(), **details}
    atomic_write(Path(output_dir) / STATUS, json.dumps(record, indent=2).encode())


def machine() -> dict:
    """Where a run's times were measured: host name and compute device."""
    if torch.cuda.is_available():
        device = f"{torch.cuda.get_device_name()} (CUDA {torch.version.cuda})"
    else:
        device = f"CPU ({os.cpu_count()} cores, {torch.get_num_threads()} torch threads)"
    return {"host": socket.gethostname(), "device": device}


def hparam_value(value):
    """A value TensorBoard's HPARAMS view accepts (bool, number or string)."""
    return value if isinstance(value, bool | int | float | str) else json.dumps(value)


def pixels(image: Tensor) -> np.ndarray:
    """8-bit pixels [H, W] or [H, W, 3] (uint8) of values in [0, 1], rounded as ``quantize`` rounds."""
    return (quantize(image) * 255).to(torch.uint8).cpu().numpy()


def png_bytes(image: Tensor) -> bytes:
    """An 8-bit PNG of [H, W] or [H, W, 3] values in [0, 1]."""
    return iio.imwrite("<bytes>", pixels(image), extension=".png")


def depth_image(depth: Tensor, opacity: Tensor, near: float, far: float) -> Tensor:
    """Depth [H, W] as a grey image, near white and far black, faded by opacity [H, W] so that
    empty space (whose depth is the mean of vanishing weights) is black: [H, W] in [0, 1]."""
    return ((far - depth) / (far - near)).clamp(0, 1) * opacity.clamp(0, 1)


IMAGES = ("rgb", "depth", "opacity", "target")  # what an evaluation step returns per image, besides its scores


def gather_evaluations(trainer: L.Trainer, outputs: dict) -> list[dict]:
    """The outputs of this evaluation step on every process (``NeRFModule._evaluate``: "index", "psnr",
    "ssim" and the images ``IMAGES``), one dict per process in rank order; on one process ``[outputs]``.

    Every process must call it at every step (it is a collective): Lightning's distributed sampler
    gives each process the same number of images, repeating some where they do not divide evenly,
    so callers keep the first result for each image index. Scores travel as float64, exactly."""
    if trainer.world_size == 1:
        return [outputs]
    images = outputs["rgb"]
    numbers = torch.tensor([outputs["index"], outputs["psnr"], outputs["ssim"]], dtype=torch.float64,
                           device=images.device)
    gathered = {key: trainer.strategy.all_gather(outputs[key]) for key in IMAGES}  # each [world size, ...]
    numbers = trainer.strategy.all_gather(numbers)  # [world size, 3]
    return [{"index": int(numbers[r, 0]), "psnr": float(numbers[r, 1]), "ssim": float(numbers[r, 2]),
             **{key: gathered[key][r] for key in IMAGES}} for r in range(trainer.world_size)]


def image_means(scores: dict[int, dict[str, float]]) -> dict[str, float]:
    """Means of per-image scores ``{index: {"psnr": ..., "ssim": ...}}``, in image order."""
    ordered = [scores[index] for index in sorted(scores)]
    return {name: float(np.mean([s[name] for s in ordered])) for name in ("psnr", "ssim")}


class RunRecorder(L.Callback):
    """Writes a run's metrics, results and test renders; times the training in wall-clock seconds;
    logs ``val/psnr``, ``val/ssim``, ``test/psnr``, ``test/ssim`` (means over the images).

    The elapsed time and the last validation PSNR are part of the checkpoint, so a resumed run keeps
    counting from where it stopped, and a test in processes that did not train (``trainer=ddp`` spawns
    new ones for ``trainer.test``) reports the step, time and validation of the checkpoint it tests. At
    the end of training the last checkpoint is written again, after the last validation: Lightning's
    ``ModelCheckpoint`` keeps the one of its last save, taken before that validation (or at an earlier
    step where ``scale.steps`` is not a multiple of ``scale.val_every``).
    """

    def __init__(self, output_dir: str, choices: dict, run_config: dict | None = None,
                 overrides: list[str] = ()):
        self.output_dir = Path(output_dir)
        self.choices, self.run_config, self.overrides = dict(choices), run_config, list(overrides)
        self.last_val_psnr: float | None = None
        self.elapsed_s, self._started, self.steps, self.trained = 0.0, None, 0, False
        self._scores: dict[int, dict[str, float]] = {}  # image index -> its psnr and ssim

    def wall_time_s(self) -> float:
        return self.elapsed_s + (time.perf_counter() - self._started if self._started is not None else 0.0)

    def on_fit_start(self, trainer, pl_module):
        """Declare the run's hyper-parameters (its choices and overrides) for TensorBoard's HPARAMS view.

        The summaries are written directly rather than through ``TensorBoardLogger.log_hyperparams``,
        which would also log the metrics' placeholder values as scalars at step 0."""
        if isinstance(trainer.logger, TensorBoardLogger) and trainer.is_global_zero:
            params = {**self.choices, **dict(o.lstrip("+~").split("=", 1) for o in self.overrides if "=" in o)}
            params = {key: hparam_value(value) for key, value in params.items()}
            writer = trainer.logger.experiment
            for summary in hparams_summaries(params, dict.fromkeys(HPARAM_METRICS, 0.0)):
                writer.file_writer.add_summary(summary)

    def on_train_start(self, trainer, pl_module):
        self._started = time.perf_counter()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.steps = trainer.global_step  # the step of the weights that the evaluations score

    def on_train_end(self, trainer, pl_module):
        self.elapsed_s, self._started, self.steps = self.wall_time_s(), None, trainer.global_step
        self.trained = True
        checkpoint = trainer.checkpoint_callback
        if checkpoint is not None and checkpoint.last_model_path:  # none yet: ModelCheckpoint saves it next
            trainer.save_checkpoint(checkpoint.last_model_path)

    def state_dict(self) -> dict:
        return {"elapsed_s": self.wall_time_s(), "last_val_psnr": self.last_val_psnr}

    def load_state_dict(self, state_dict: dict) -> None:
        if not self.trained:  # a test after training in this process keeps what it measured
            self.elapsed_s, self.last_val_psnr = state_dict["elapsed_s"], state_dict.get("last_val_psnr")

    def on_load_checkpoint(self, trainer, pl_module, checkpoint: dict) -> None:
        if not self.trained:
            self.steps = checkpoint["global_step"]

    def _collect(self, trainer, pl_module, outputs: dict, split: str) -> None:
        for item in gather_evaluations(trainer, outputs):
            index = item["index"]
            if index in self._scores:  # a repeat of the distributed sampler's padding
                continue
            self._scores[index] = {"psnr": item["psnr"], "ssim": item["ssim"]}
            if trainer.is_global_zero:
                self._write_images(trainer, pl_module, item, split)

    def _write_images(self, trainer, pl_module, item: dict, split: str) -> None:
        index, renderer = item["index"], pl_module.renderer
        depth = depth_image(item["depth"], item["opacity"], renderer.near, renderer.far)
        if split == "test":
            atomic_write(self.output_dir / "test" / f"r_{index}.png", png_bytes(item["rgb"]))
            atomic_write(self.output_dir / "test" / f"r_{index}_depth.png", png_bytes(depth))
        if index < 4 and trainer.logger is not None and not trainer.sanity_checking:
            side_by_side = torch.cat([item["rgb"], item["target"], depth[..., None].expand(-1, -1, 3)], 1)
            trainer.logger.experiment.add_image(f"{split}/render_target_depth/{index}", quantize(side_by_side),
                                                self.steps, dataformats="HWC")

    def _flush(self, trainer, split: str) -> dict:
        """The means of the images scored since the last flush; rank 0 appends them to ``metrics.jsonl``
        and logs them at the step of the weights scored."""
        means, self._scores = image_means(self._scores), {}
        if trainer.is_global_zero:
            record = {"step": self.steps, "wall_time_s": self.wall_time_s(), "split": split, **means}
            path = self.output_dir / "metrics.jsonl"
            previous = path.read_bytes() if path.exists() else b""
            atomic_write(path, previous + (json.dumps(record) + "\n").encode())
            if trainer.logger is not None:
                trainer.logger.log_metrics({f"{split}/{name}": value for name, value in means.items()}, self.steps)
        return means

    def on_validation_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0):
        if not trainer.sanity_checking:
            self._collect(trainer, pl_module, outputs, "val")

    def on_validation_epoch_end(self, trainer, pl_module):
        if not trainer.sanity_checking:
            self.last_val_psnr = self._flush(trainer, "val")["psnr"]

    def on_test_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0):
        self._collect(trainer, pl_module, outputs, "test")

    def on_test_epoch_end(self, trainer, pl_module):
        means, steps = self._flush(trainer, "test"), self.steps
        if not trainer.is_global_zero:
            return
        renderer, batch_rays = pl_module.renderer, getattr(trainer.datamodule, "batch_rays", None)
        results = {
            "test_psnr": means["psnr"], "test_ssim": means["ssim"], "val_psnr": self.last_val_psnr,
            "train_time_s": self.elapsed_s, "steps": steps,
            "time_per_step_s": self.elapsed_s / max(steps, 1),
            "rays_per_s": batch_rays * steps / self.elapsed_s if batch_rays and self.elapsed_s > 0 else None,
            "batch_rays": batch_rays, "processes": trainer.world_size,
            "n_params": sum(p.numel() for p in pl_module.parameters()),
            "evaluations_per_ray": renderer.evaluations_per_ray,
            "machine": machine(), "choices": self.choices, "overrides": self.overrides,
            "config": self.run_config,
        }
        atomic_write(self.output_dir / RESULTS, json.dumps(results, indent=2).encode())


def find_run(path: str | Path) -> tuple[Path, Path]:
    """``(run directory, checkpoint)`` of ``path``: a run directory (its ``checkpoints/last.ckpt``) or a
    checkpoint file in one (``RUN_DIR/checkpoints/NAME.ckpt``: the run directory two levels up)."""
    path = Path(path)
    if not path.exists():
        raise NerfexpError(f"{path} does not exist: expected a run directory or a checkpoint file in one")
    run_dir, checkpoint = (path, path / LAST_CHECKPOINT) if path.is_dir() else (path.parent.parent, path)
    if not (run_dir / RUN_CONFIG).is_file():
        raise NerfexpError(f"{run_dir} is not a run directory: it has no {RUN_CONFIG}")
    if not checkpoint.is_file():
        raise NerfexpError(f"{checkpoint} does not exist: the run in {run_dir} has saved no checkpoint")
    return run_dir, checkpoint


def run_config(run_dir: Path, overrides: list[str] = ()) -> DictConfig:
    """The config a run used (its ``RUN_CONFIG``), with ``KEY=VALUE`` ``overrides`` of existing keys
    (e.g. ``data.root=...`` for a scene that moved)."""
    cfg = OmegaConf.load(Path(run_dir) / RUN_CONFIG)
    OmegaConf.set_struct(cfg, True)  # an override of a key the run does not have is a typo, not a new key
    try:
        return OmegaConf.merge(cfg, OmegaConf.from_dotlist(list(overrides)))
    except OmegaConfBaseException as error:
        raise ConfigError(f"cannot apply {' '.join(overrides)} to {Path(run_dir) / RUN_CONFIG}: "
                          f"{str(error).splitlines()[0]}") from None


def load_module(cfg: DictConfig, checkpoint: Path) -> tuple[L.LightningModule, int]:
    """The run's model (``cfg.model``) with the weights of ``checkpoint``, on the CPU, and the number of
    optimizer steps it had taken."""
    fill_ray_bounds(cfg)  # a run's saved config holds null where the scene chose near and far
    module = instantiate(cfg.model)
    try:
        state = torch.load(checkpoint, map_location="cpu", weights_only=True)
        module.load_state_dict(state["state_dict"])
    except (OSError, RuntimeError, KeyError, EOFError, pickle.UnpicklingError) as error:
        raise NerfexpError(f"{checkpoint}: not a checkpoint of this run's model "
                           f"({type(error).__name__}: {str(error).splitlines()[0]})") from None
    return module, state["global_step"]


class EvalRecorder(L.Callback):
    """Scores a checkpoint on the test split: ``eval.json`` in ``output_dir`` holds ``test_psnr``,
    ``test_ssim`` (means over the test views, as in ``results.json``), ``psnr`` and ``ssim`` per view,
    the ``checkpoint``, its ``step`` and the ``machine``."""

    def __init__(self, output_dir: str | Path, checkpoint: str | Path, step: int):
        self.output_dir, self.checkpoint, self.step = Path(output_dir), Path(checkpoint), step
        self._scores: dict[int, dict[str, float]] = {}  # image index -> its psnr and ssim

    def on_test_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0):
        for item in gather_evaluations(trainer, outputs):
            self._scores.setdefault(item["index"], {"psnr": item["psnr"], "ssim": item["ssim"]})

    def on_test_epoch_end(self, trainer, pl_module):
        if not trainer.is_global_zero:
            return
        means, views = image_means(self._scores), sorted(self._scores)
        results = {"test_psnr": means["psnr"], "test_ssim": means["ssim"],
                   **{name: [self._scores[i][name] for i in views] for name in ("psnr", "ssim")},
                   "checkpoint": str(self.checkpoint.resolve()), "step": self.step,
                   "processes": trainer.world_size, "machine": machine()}
        atomic_write(self.output_dir / EVAL, json.dumps(results, indent=2).encode())
