"""Lightning callbacks of a training run that are not about NeRF: CPU denormals flushed while it trains."""

import lightning as L
import torch


def flushes_denormals() -> bool:
    """Whether this thread's CPU arithmetic flushes float32 denormals to zero (torch sets it, but has no getter)."""
    return (torch.tensor(torch.finfo(torch.float32).tiny) / 2).item() == 0.0


class FlushDenormals(L.Callback):
    """Flushes CPU denormals to zero while ``fit`` runs, and puts the previous setting back after it,
    also when it fails.

    exp(-optical depth) behind surfaces and the densities of empty space produce float32 denormals
    (below 1.2e-38), which slow the CPU's backward pass down (measured in docs/results/default_run.md);
    flushing them costs nothing in accuracy at these magnitudes. The setting is process-wide, so it is
    scoped to training: other code in the process (a notebook, the test suite's float64 references)
    keeps IEEE denormals.
    """

    def __init__(self):
        self._previous: bool | None = None

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._previous = flushes_denormals()
        torch.set_flush_denormal(True)

    def _restore(self) -> None:
        if self._previous is not None:
            torch.set_flush_denormal(self._previous)
            self._previous = None

    def on_fit_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._restore()

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        self._restore()
