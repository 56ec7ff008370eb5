"""A run or a sweep ended by a signal exits with 128 + the signal, and the job's status names it."""

import logging
import os
import signal
import time
from pathlib import Path

import pytest

from nerfexp.commands.signals import Signalled, job_signals, received_signal
from tests.helpers import read_json, start_nerfexp

LONG = ["scale.steps=100000", "scale.val_every=5"]  # far longer than the test waits; a validation every 5 steps


def wait_for_training(log: Path, timeout_s: float = 120) -> None:
    """Until the run's log shows a validation (training is under way, inside Lightning's ``fit``)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if log.exists() and "validation PSNR" in log.read_text():
            return
        time.sleep(0.2)
    raise AssertionError(f"no validation in {log} after {timeout_s} s")


@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_ends_a_run_with_128_plus_it_and_the_status_names_it(tmp_path, tiny, signum):
    process = start_nerfexp(*tiny, *LONG, f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    wait_for_training(tmp_path / "nerfexp.log")
    process.send_signal(signum)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 128 + signum, stderr[-3000:]
    status = read_json(tmp_path / "status.json")
    name = signal.Signals(signum).name
    assert (status["state"], status["signal"], status["error"]) == ("failed", name, f"ended by {name}")


@pytest.mark.slow
def test_sigterm_ends_a_sweep_with_143_and_no_later_job_starts(tmp_path, tiny):
    process = start_nerfexp("-m", *tiny, *LONG, "seed=0,1", f"hydra.sweep.dir={tmp_path}", cwd=tmp_path)
    wait_for_training(tmp_path / "0" / "nerfexp.log")
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 143, stderr[-3000:]
    assert read_json(tmp_path / "0" / "status.json")["signal"] == "SIGTERM"
    assert not (tmp_path / "1").exists()


def test_in_a_launchers_job_sigterm_raises_and_the_time_limit_notice_is_only_logged(monkeypatch, caplog):
    monkeypatch.setenv("SUBMITIT_EXECUTOR", "slurm")  # as submitit's sbatch script exports it
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGUSR2)
    with caplog.at_level(logging.WARNING, logger="nerfexp"), job_signals():
        os.kill(os.getpid(), signal.SIGUSR2)
        time.sleep(0.05)  # the handler runs in this thread at its next instruction
        assert "SIGUSR2: SLURM's notice that the job nears its time limit" in caplog.text
        with pytest.raises(Signalled):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)
        assert received_signal() == "SIGTERM"
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGUSR2)) == before


def test_the_notice_is_the_signal_submitit_is_told_to_use_and_outside_a_job_nothing_changes(monkeypatch, caplog):
    before = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGUSR1, signal.SIGUSR2)}
    with job_signals():
        assert {s: signal.getsignal(s) for s in before} == before
    monkeypatch.setenv("SUBMITIT_EXECUTOR", "slurm")
    monkeypatch.setenv("SUBMITIT_PREEMPT_SIGNAL", "USR1")
    with caplog.at_level(logging.WARNING, logger="nerfexp"), job_signals():
        assert signal.getsignal(signal.SIGUSR2) == before[signal.SIGUSR2]
        os.kill(os.getpid(), signal.SIGUSR1)
        time.sleep(0.05)
    assert "SIGUSR1: SLURM's notice" in caplog.text
