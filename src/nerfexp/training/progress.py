"""The progress bars of nerfexp's trainers: optimizer steps of the whole run, not batches of an epoch, and drawn
only on a terminal (a test-time fit's bar, under the test's: ``nerfexp.scoring.scorer.fit_progress_bar``)."""

import sys

from lightning.pytorch.callbacks import Callback, TQDMProgressBar
from omegaconf import DictConfig


class StepProgressBar(TQDMProgressBar):
    """Lightning's tqdm bars, with the training bar counting the run's steps (``training 1200/4000``,
    its loss and PSNR after them). nerfexp trains on one endless epoch, for which Lightning's own bar
    reads "Epoch 0" with no total. A run resumed at step k starts its bar at k.

    ``enabled`` None: on where standard output (the bars' stream) is a terminal, off where it is a file
    or a pipe (a SLURM log), which then gets one line per validation from ``RunRecorder`` instead of
    carriage-return redraws."""

    def __init__(self, enabled: bool | None = None, refresh_rate: int = 1):
        super().__init__(refresh_rate=refresh_rate)
        if not (sys.stdout.isatty() if enabled is None else enabled):
            self.disable()

    def on_train_epoch_start(self, trainer, *_) -> None:
        bar = self.train_progress_bar
        bar.reset(total=trainer.max_steps)
        bar.initial = bar.n = trainer.global_step  # tqdm's rate counts from ``initial``
        bar.unit = "step"
        bar.set_description("training")

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx: int) -> None:
        bar = self.train_progress_bar
        if self._should_update(trainer.global_step, trainer.max_steps) and not bar.disable:
            bar.n = trainer.global_step
            bar.set_postfix(self.get_metrics(trainer, pl_module))  # refreshes the bar

    def get_metrics(self, trainer, pl_module) -> dict:
        """The values logged with ``prog_bar=True`` (``train/loss``, ``train/psnr``), without the
        logger's version number."""
        metrics = super().get_metrics(trainer, pl_module)
        metrics.pop("v_num", None)
        return metrics


def progress_bars(trainer: DictConfig) -> list[Callback]:
    """The progress-bar callback of a Lightning trainer built from the config ``trainer``: a
    ``StepProgressBar`` (on only where standard output is a terminal) where the config shows bars, none
    where it does not (Lightning refuses a bar callback then). Every trainer nerfexp makes (training,
    ``nerfexp-eval``) takes it, since Lightning's own bar draws on standard output whatever it is."""
    return [StepProgressBar()] if trainer.get("enable_progress_bar", True) else []
