"""A run or a sweep ended by a signal exits with 128 + the signal, and the job's status names it."""

import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import tomllib

from nerfexp.commands.signals import Signalled, ending_signals, job_signals, received_signal
from tests.helpers import REPO, command, read_json, start_nerfexp

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


# Ctrl-C while a command is still importing its libraries: the entry points pyproject.toml declares
# (nerfexp.commands.start) set the handlers first, so even then it is one line and 130.

ENTRY_POINTS = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]


def wait_for_torch(process: subprocess.Popen, timeout_s: float = 120) -> None:
    """Until ``process`` has loaded torch's library: it is importing its command's modules (the entry point,
    which imports nothing heavy, has run), seconds before the command can do anything."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and process.poll() is None:
        if "libtorch" in Path(f"/proc/{process.pid}/maps").read_text():
            return
        time.sleep(0.01)
    raise AssertionError(f"the process did not load torch within {timeout_s} s (exit status {process.poll()})")


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="reads which libraries a process loaded from /proc")
@pytest.mark.parametrize(("script", "signum"), [*((script, signal.SIGINT) for script in sorted(ENTRY_POINTS)),
                                                ("nerfexp-report", signal.SIGTERM)])
def test_a_signal_while_a_command_starts_is_its_stopped_line_and_128_plus_it(script, signum, tmp_path):
    module, function = ENTRY_POINTS[script].split(":")
    # what the wrapper `pip install` writes for the entry point runs, whatever version is installed here
    wrapper = f"import sys; sys.argv[0] = {script!r}; from {module} import {function}; sys.exit({function}())"
    _, env = command(script)
    process = subprocess.Popen([sys.executable, "-c", wrapper, str(tmp_path / "no_run")], cwd=tmp_path, env=env,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    wait_for_torch(process)
    process.send_signal(signum)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 128 + signum, stderr[-3000:]
    said = [f"{script}: stopped ({signal.Signals(signum).name})"]
    assert "Traceback" not in stderr and stderr.strip().splitlines() == said, stderr
    assert list(tmp_path.iterdir()) == []


def test_a_block_inside_another_leaves_the_line_to_it(capsys):
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(SystemExit) as ended, ending_signals("outer"), ending_signals("inner"):
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(5)
    assert ended.value.code == 130 and received_signal() == "SIGINT"
    assert capsys.readouterr().err.splitlines() == ["outer: stopped (SIGINT)"]
    assert signal.getsignal(signal.SIGINT) == before
