"""Lightning callbacks of a training run that are not about NeRF: CPU denormals flushed while it trains, and a
launcher's job's SIGTERM handler kept in place of Lightning's."""

import signal

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


class KeepSigtermHandler(L.Callback):
    """Puts back, once Lightning has set its own, the SIGTERM handler the process had when ``fit`` or ``test``
    began (a launcher's job: ``nerfexp.commands.signals.job_signals``'s, which records the signal and raises).

    Lightning's handler broadcasts from rank 0 inside the handler itself. SLURM sends SIGTERM to every task
    of a job at its time limit; a process whose handler runs while another is still inside a collective
    (its Python handler waits for the collective to return) starts a broadcast that collective never
    matches, and both wait until SLURM kills them, with nothing recorded. With nerfexp's handler the first
    process to see the signal ends, its peers' collective fails for want of it, and each records SIGTERM."""

    def __init__(self):
        self._handler = None

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        self._handler = signal.getsignal(signal.SIGTERM)

    def _restore(self) -> None:
        if self._handler is not None:
            signal.signal(signal.SIGTERM, self._handler)

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._restore()  # Lightning registers its handlers after the setup hooks, before the first step

    def on_test_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._restore()
