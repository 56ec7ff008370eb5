"""What nerfexp records beyond scalars, written to whatever Lightning logger a run has (``conf/logger/``):
images, hyper-parameters and the run's labels (tags, notes). Lightning's loggers share ``log_metrics`` and
``log_hyperparams`` but not images or labels, so each kind gets its own writer:

- TensorBoard: ``add_image``; the hyper-parameters as HPARAMS summaries (its HPARAMS view);
- Weights & Biases: ``WandbLogger.log_image``;
- MLflow: ``MlflowClient.log_image``, an image series per key;
- CSV and any other logger: PNG files, ``LOG_DIR/images/<key>/step_<step>.png`` (``LOG_DIR``: the
  logger's ``log_dir``, or ``fallback_dir`` where it has none).
"""

import json
from pathlib import Path

import numpy as np
from lightning.pytorch.loggers import Logger, MLFlowLogger, TensorBoardLogger, WandbLogger
from torch.utils.tensorboard.summary import hparams as hparams_summaries

from nerfexp.files import atomic_write
from nerfexp.pixels import png_bytes

# TensorBoard's HPARAMS metric columns (LPIPS's are empty for runs that do not score it)
HPARAM_METRICS = ("val/psnr", "val/ssim", "val/lpips", "test/psnr", "test/ssim", "test/lpips")


def hparam_value(value):
    """A value every logger's hyper-parameters accept (bool, number or string)."""
    return value if isinstance(value, bool | int | float | str) else json.dumps(value)


def log_hyperparams(logger: Logger, params: dict) -> None:
    """Declare a run's hyper-parameters ``params`` (values: anything JSON can write) to ``logger``.

    TensorBoard's summaries are written directly rather than through ``TensorBoardLogger.log_hyperparams``,
    which would also log the metrics' placeholder values as scalars at step 0."""
    params = {key: hparam_value(value) for key, value in params.items()}
    if isinstance(logger, TensorBoardLogger):
        writer = logger.experiment
        for summary in hparams_summaries(params, dict.fromkeys(HPARAM_METRICS, 0.0)):
            writer.file_writer.add_summary(summary)
    else:
        logger.log_hyperparams(params)


def log_labels(logger: Logger, tags: list[str], notes: str | None) -> None:
    """Give a run's labels (``nerfexp.rundir.labels``) to ``logger`` where it keeps them apart from the
    hyper-parameters (which hold them too): W&B's run ``tags`` and ``notes``; MLflow's run tags ``tags`` (the
    list as JSON) and ``mlflow.note.content`` (the run's description in MLflow's UI). TensorBoard and CSV have
    only the hyper-parameters."""
    if isinstance(logger, WandbLogger):
        run = logger.experiment
        if tags:
            run.tags = tuple(tags)
        if notes is not None:
            run.notes = notes
    elif isinstance(logger, MLFlowLogger):
        named = {"tags": json.dumps(tags) if tags else None, "mlflow.note.content": notes}
        for key, value in named.items():
            if value is not None:
                logger.experiment.set_tag(logger.run_id, key, value)


def log_image(logger: Logger, key: str, pixels: np.ndarray, step: int, fallback_dir: Path) -> None:
    """Record 8-bit RGB ``pixels`` [H, W, 3] (uint8) under ``key`` at training step ``step``."""
    if isinstance(logger, TensorBoardLogger):
        logger.experiment.add_image(key, pixels, step, dataformats="HWC")
    elif isinstance(logger, WandbLogger):
        logger.log_image(key, [pixels], step=step)
    elif isinstance(logger, MLFlowLogger):
        logger.experiment.log_image(logger.run_id, pixels, key=key, step=step)
    else:
        root = Path(logger.log_dir) if getattr(logger, "log_dir", None) else fallback_dir
        atomic_write(root / "images" / key / f"step_{step:07d}.png", png_bytes(pixels))


def finish(logger: Logger | bool, succeeded: bool) -> None:
    """End the logger's run where its library must be told: a W&B run not finished before the process
    exits is left incomplete (its service stops first). The other loggers are closed by Lightning."""
    if isinstance(logger, WandbLogger):
        import wandb  # installed: the logger was built

        wandb.finish(exit_code=0 if succeeded else 1)  # the active run, if it was started
