"""What a training run and an evaluation record: the recorders, Lightning callbacks that write a run's
files (their names and places: ``nerfexp.rundir``) and log its scores.

In a distributed run (``trainer=ddp``) each process evaluates its share of the images; the recorders
gather every image's scores and renders to all processes (``gather_evaluations``), and only global
rank 0 writes files and logs, so the numbers are those of one process scoring every image.
"""

import json
import time
from pathlib import Path

import lightning as L
import numpy as np
import torch
from lightning.pytorch.loggers import TensorBoardLogger
from torch.utils.tensorboard.summary import hparams as hparams_summaries

from nerfexp.files import atomic_write
from nerfexp.pixels import depth_image, png_bytes, quantize, to_uint8
from nerfexp.rundir import EVAL, RESULTS, TEST_DIR, append_metrics, checkpoint_record, machine, write_json

HPARAM_METRICS = ("val/psnr", "val/ssim", "test/psnr", "test/ssim")  # the HPARAMS view's metric columns


def hparam_value(value):
    """A value TensorBoard's HPARAMS view accepts (bool, number or string)."""
    return value if isinstance(value, bool | int | float | str) else json.dumps(value)


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
            atomic_write(self.output_dir / TEST_DIR / f"r_{index}.png", png_bytes(to_uint8(item["rgb"])))
            atomic_write(self.output_dir / TEST_DIR / f"r_{index}_depth.png", png_bytes(to_uint8(depth)))
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
            append_metrics(self.output_dir, record)
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
        if trainer.ckpt_path is not None:  # the weights scored: the checkpoint the test loaded
            results["checkpoint"] = checkpoint_record(self.output_dir, Path(trainer.ckpt_path))
        write_json(self.output_dir / RESULTS, results)


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
        write_json(self.output_dir / EVAL, results)
