"""Lightning callbacks of a training run that are not about NeRF: CPU denormals flushed while it trains, a
launcher's job's SIGTERM handler kept in place of Lightning's, and torch's threads following the machine's load."""

import logging
import signal
import time

import lightning as L
import torch

from nerfexp.denormals import flushes_denormals, set_flush_denormal_everywhere
from nerfexp.machine_share import FOLLOW_WINDOW_S, Sample, follow_load, sample

log = logging.getLogger(__name__)


class FlushDenormals(L.Callback):
    """Flushes CPU denormals to zero while ``fit`` runs, and puts the previous setting back after it,
    also when it fails.

    exp(-optical depth) behind surfaces and the densities of empty space produce float32 denormals
    (below 1.2e-38), which slow the CPU's backward pass down (measured in docs/results/default_run.md);
    flushing them costs nothing in accuracy at these magnitudes. The setting is a thread's, so it is set on every
    thread of torch's OpenMP team (``set_flush_denormal_everywhere``: torch's own call reaches only the calling
    thread, and the workers kept computing on denormals), and it is scoped to training: other code in the process (a
    notebook, the test suite's float64 references) keeps IEEE denormals.
    """

    def __init__(self):
        self._previous: bool | None = None

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._previous = flushes_denormals()
        if not set_flush_denormal_everywhere(True):
            log.info("CPU denormals flushed on the training thread only: no OpenMP runtime found in this process to "
                     "reach torch's other threads")

    def _restore(self) -> None:
        if self._previous is not None:
            set_flush_denormal_everywhere(self._previous)
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


class ThreadsFollowLoad(L.Callback):
    """Looks at the machine every ``window_s`` seconds of training and, where other processes now keep more or fewer
    of the ``cpus`` this run may use busy than its thread count leaves them (``follow_load``), sets torch's intra-op
    threads to the rest: a neighbour that starts after the run does not make its OpenMP threads wait on each other
    for the rest of it (a collapse of many times, docs/acceleration.md), and a busy moment at the start that has
    passed does not keep it on fewer threads. Each change is said in one line and appended to ``changes``
    (``{"step", "threads", "other_load"}``: results.json's ``thread_changes``).

    For a single run whose threads were chosen automatically (``ThreadChoice.follows_load``), in one process: the
    processes of a distributed run would count each other as neighbours. The thread count may change the order of
    a parallel sum, so such a run's numbers may differ from an undisturbed one's in their last digits."""

    def __init__(self, cpus: int, changes: list[dict], window_s: float = FOLLOW_WINDOW_S):
        self.cpus, self.changes, self.window_s = cpus, changes, window_s
        self._last: Sample | None = None

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._last = sample() if trainer.world_size == 1 else None

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs, batch, batch_idx) -> None:
        if self._last is None:
            return
        if time.perf_counter() - self._last.wall_s < self.window_s:  # /proc/stat read only once the window passed
            return
        now = sample()
        elapsed = now.wall_s - self._last.wall_s
        if elapsed < self.window_s:
            return
        threads = torch.get_num_threads()
        change = follow_load(threads, self.cpus, self._last, now)
        self._last = now
        if change is None:
            return
        wanted, load = change
        torch.set_num_threads(wanted)
        self.changes.append({"step": trainer.global_step, "threads": wanted, "other_load": load})
        log.log(logging.WARNING if wanted < threads else logging.INFO,
                "torch threads: %d -> %d at step %d: other processes kept %.1f of the %d CPUs this run may use busy "
                "over the last %.0f s (auto; threads=N fixes the count)", threads, wanted, trainer.global_step, load,
                self.cpus, elapsed)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._last = None
