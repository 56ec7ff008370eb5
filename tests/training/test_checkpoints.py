"""Checkpoints are written whole wherever TMPDIR points: staged beside the checkpoint and renamed over it,
so a process killed during a save leaves the previous checkpoint whole (nerfexp.training.checkpoints)."""

import errno
import os
import random
import shutil
import signal
import tempfile
import time
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate
from lightning.pytorch.plugins.io import TorchCheckpointIO

from nerfexp.files import WriteError
from nerfexp.training.checkpoints import AtomicCheckpointIO
from nerfexp.training.precision import fill_precision
from tests.helpers import fill_disk, small_disk

OTHER_FILE_SYSTEM = Path("/dev/shm")  # a tmpfs where /tmp and the runs are on a disk: a cluster node's scratch
WEIGHTS = 8 * 2**20  # float32 values: a 32 MiB checkpoint, long enough to write that a kill lands inside it
KILLS = 6


@pytest.fixture
def other_tmpdir(tmp_path, monkeypatch) -> Path:
    """TMPDIR set to a folder on another file system than ``tmp_path`` (where the checkpoints go), and read
    again by ``tempfile``; removed afterwards with whatever a save left there."""
    scratch = Path(tempfile.mkdtemp(dir=OTHER_FILE_SYSTEM, prefix="nerfexp-test-"))
    try:
        assert scratch.stat().st_dev != tmp_path.stat().st_dev, f"{scratch} is on the file system of {tmp_path}"
        monkeypatch.setenv("TMPDIR", str(scratch))
        monkeypatch.setattr(tempfile, "tempdir", None)  # tempfile caches TMPDIR once read
        assert tempfile.gettempdir() == str(scratch)
        yield scratch
    finally:
        shutil.rmtree(scratch)


@pytest.mark.parametrize(("checkpoint_io", "staged_beside"), [(AtomicCheckpointIO, True),
                                                              (TorchCheckpointIO, False)])  # Lightning's: TMPDIR
def test_a_save_stages_its_file_beside_the_checkpoint_never_in_tmpdir(checkpoint_io, staged_beside, other_tmpdir,
                                                                      tmp_path, monkeypatch):
    destination = tmp_path / "checkpoints" / "last.ckpt"
    moves = []  # (the file moved into place, what TMPDIR held at that moment)

    def recording(move):
        def recorded(source, target, *args, **kwargs):
            if Path(target) == destination:
                moves.append((Path(source), sorted(other_tmpdir.iterdir())))
            return move(source, target, *args, **kwargs)
        return recorded

    monkeypatch.setattr(os, "replace", recording(os.replace))  # nerfexp's atomic_file
    monkeypatch.setattr(shutil, "move", recording(shutil.move))  # fsspec's transaction, under Lightning's save
    for step in range(2):  # the second save replaces a checkpoint
        checkpoint_io().save_checkpoint({"step": step, "weights": torch.arange(1000.0)}, destination)
    assert len(moves) == 2
    for source, in_tmpdir in moves:
        assert (source.parent == destination.parent) == staged_beside
        assert (in_tmpdir == []) == staged_beside
    assert torch.load(destination, weights_only=True)["step"] == 1
    assert sorted(p.name for p in destination.parent.iterdir()) == ["last.ckpt"]  # nothing of the save left


def test_a_save_that_fails_removes_its_own_file_and_nothing_else(other_tmpdir, tmp_path):
    destination = tmp_path / "checkpoints" / "last.ckpt"
    AtomicCheckpointIO().save_checkpoint({"step": 0, "weights": torch.ones(1000)}, destination)
    other = destination.parent / ".last.ckpt.another-save.tmp"  # as another process's save would name its own
    other.write_bytes(b"not this save's")
    with pytest.raises(AttributeError, match="pickle"):  # inside torch.save, its temporary file made
        AtomicCheckpointIO().save_checkpoint({"weights": torch.zeros(1000), "step": lambda: 1}, destination)
    assert sorted(destination.parent.iterdir()) == [other, destination]
    assert other.read_bytes() == b"not this save's"
    assert torch.equal(torch.load(destination, weights_only=True)["weights"], torch.ones(1000))


def saving_process(checkpoint_io, destination: Path, versions: list[torch.Tensor]) -> tuple[int, int]:
    """A forked process that saves checkpoints {"version": n, "weights": versions[n % 2]} to ``destination``
    with ``checkpoint_io``, n = 0, 1, ..., until it is killed, writing a byte to a pipe after each save.
    Returns its process id and the pipe's reading end. Forked, it starts without importing anything."""
    reading, writing = os.pipe()
    pid = os.fork()
    if pid == 0:
        try:
            os.close(reading)
            version = 0
            while True:
                checkpoint_io.save_checkpoint({"version": version, "weights": versions[version % 2]}, destination)
                os.write(writing, b".")
                version += 1
        finally:
            os._exit(1)  # never back into pytest
    os.close(writing)
    return pid, reading


def read_saves(reading: int, count: int) -> None:
    """Wait until the saving process reported ``count`` more saves; an error where it ended first."""
    for _ in range(count):
        assert os.read(reading, 1) == b".", "the saving process ended before it was killed"


def kill_during_a_save(checkpoint_io, destination: Path, versions: list[torch.Tensor], rng: random.Random) -> bool:
    """Start ``saving_process``; after two saves (the first checkpoint is whole) SIGKILL it at a random
    moment of the next two saves, or as soon as ``destination`` is seen shorter than a whole checkpoint, whichever comes
    first. Returns whether ``destination`` then holds a whole checkpoint, the last one saved (or the one
    whose save had just renamed it into place)."""
    pid, reading = saving_process(checkpoint_io, destination, versions)
    try:
        read_saves(reading, 1)
        start = time.monotonic()
        read_saves(reading, 1)
        deadline = time.monotonic() + rng.uniform(0, 2 * (time.monotonic() - start))  # in the next two saves
        while time.monotonic() < deadline and destination.stat().st_size > versions[0].nbytes:
            pass
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        saved = 2 + len(os.read(reading, 1 << 20))  # the saves it reported
    finally:
        os.close(reading)
    try:
        checkpoint = torch.load(destination, map_location="cpu", weights_only=True)
    except Exception:  # torn, whatever the loader says about it
        return False
    version = checkpoint["version"]
    return version in (saved - 1, saved) and torch.equal(checkpoint["weights"], versions[version % 2])


@pytest.mark.parametrize(("checkpoint_io", "whole"), [(AtomicCheckpointIO, True),
                                                      (TorchCheckpointIO, False)])  # Lightning's tears
def test_a_kill_during_a_save_leaves_the_previous_checkpoint_whole(checkpoint_io, whole, other_tmpdir, tmp_path):
    destination = tmp_path / "checkpoints" / "last.ckpt"
    versions = [torch.zeros(WEIGHTS), torch.arange(WEIGHTS, dtype=torch.float32)]
    rng = random.Random(0)
    outcomes = []
    interrupted = 0  # kills that left a save's temporary file beside the checkpoint: they landed inside a save
    for _ in range(KILLS):
        outcomes.append(kill_during_a_save(checkpoint_io(), destination, versions, rng))
        leftovers = [p for p in destination.parent.iterdir() if p != destination]
        interrupted += bool(leftovers)
        for leftover in leftovers:
            leftover.unlink()
    if whole:
        assert all(outcomes) and interrupted > 0
    else:
        assert not all(outcomes)  # the test can fail: Lightning's save, staged in TMPDIR, copies over the last


@pytest.mark.parametrize("trainer", ["default", "bf16", "ddp", "slurm"])
def test_every_trainer_config_saves_through_nerfexps_checkpoint_io(trainer, tmp_path):
    with initialize_config_module("nerfexp.conf", version_base=None):
        cfg = compose("config", overrides=[f"trainer={trainer}", "trainer.accelerator=cpu",
                                           f"trainer.devices={2 if trainer == 'ddp' else 1}",
                                           f"trainer.default_root_dir={tmp_path}"])
    fill_precision(cfg)  # as a job does before it builds the trainer
    built = instantiate(cfg.trainer, logger=False)
    assert isinstance(built.strategy.checkpoint_io, AtomicCheckpointIO)


def test_a_checkpoint_that_does_not_fit_on_the_disk_is_an_error_naming_it_and_the_last_stays(tmp_path):
    """torch.save turns the OSError of its file's write into a RuntimeError ("unexpected pos") naming
    neither; the save raises the OSError, as a WriteError naming the checkpoint."""
    with small_disk(tmp_path / "disk", "1m") as disk:
        destination = disk / "checkpoints" / "last.ckpt"
        AtomicCheckpointIO().save_checkpoint({"step": 0, "weights": torch.ones(1000)}, destination)
        before = destination.read_bytes()
        fill_disk(disk / "filler")
        with pytest.raises(WriteError) as raised:
            AtomicCheckpointIO().save_checkpoint({"step": 1, "weights": torch.zeros(1 << 16)}, destination)
        assert (raised.value.filename, raised.value.errno) == (str(destination), errno.ENOSPC)
        assert [p.name for p in destination.parent.iterdir()] == ["last.ckpt"]  # no temporary left
        assert destination.read_bytes() == before
