"""A run or a sweep ended by a signal exits with 128 + the signal, and the job's status names it."""

import signal
import time
from pathlib import Path

import pytest

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
