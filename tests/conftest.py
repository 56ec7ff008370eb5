"""Shared fixtures: the real config, shrunk to run in seconds on a CPU (``tests.helpers.TINY``), and no test
reaching the internet; the pytest-xdist workers (``-n auto``) and each one's share of the CPUs; the device that the
device-independent tests run on (``device``: ``NERFEXP_TEST_DEVICE``, the CPU where unset)."""

import os
import tempfile
from pathlib import Path

import pytest
import torch

from nerfexp.scoring import perceptual
from nerfexp.training.precision import CACHE_VARIABLE
from tests.helpers import NO_INTERNET, TINY, run_nerfexp
from tests.scoring.weights_server import refused_url

MOST_WORKERS = 4  # pytest-xdist's -n auto: each worker a torch process of its own (memory, and DDP's extra ones)
TEST_DEVICE = "NERFEXP_TEST_DEVICE"  # cpu (unset), cuda, cuda:1: where the tests taking ``device`` run
ON_DEVICE = "on_device"  # the marker of those tests (``-m on_device`` selects them: benchmarks/gpu/gpu_check.sh)


def pytest_xdist_auto_num_workers(config) -> int:
    """``-n auto`` (pyproject.toml's addopts): one worker per CPU this process may use, at most ``MOST_WORKERS``."""
    return max(1, min(len(os.sched_getaffinity(0)), MOST_WORKERS))


def pytest_configure(config) -> None:
    """In a pytest-xdist worker, torch (the worker's, and that of every command a test starts as a process,
    through OMP_NUM_THREADS) uses its share of the CPUs: workers x threads = CPUs, not workers x CPUs threads
    spinning against each other."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0"))
    if workers > 1:
        threads = max(1, len(os.sched_getaffinity(0)) // workers)
        os.environ["OMP_NUM_THREADS"] = str(threads)
        torch.set_num_threads(threads)
    # trainer.precision=auto's measurements (nerfexp.training.precision) kept apart from the user's, for this session
    # and every command it starts
    os.environ.setdefault(CACHE_VARIABLE, tempfile.mkdtemp(prefix="nerfexp-precision-"))
    chosen_device()  # a device that is misspelt or not here stops the session in one line, before any test


def chosen_device() -> torch.device:
    """``NERFEXP_TEST_DEVICE`` as a torch device (the CPU where unset); a value torch does not read as a device,
    or a CUDA device that torch does not see, is a pytest usage error naming the variable."""
    value = os.environ.get(TEST_DEVICE, "cpu")
    try:
        device = torch.device(value)
    except RuntimeError:
        device = None
    if device is None or device.type not in ("cpu", "cuda"):
        raise pytest.UsageError(f"{TEST_DEVICE}={value!r}: expected cpu or a CUDA device (cuda, cuda:N), "
                                f"or unset (cpu)")
    if device.type == "cuda" and (device.index or 0) >= torch.cuda.device_count():
        raise pytest.UsageError(f"{TEST_DEVICE}={value!r}: torch sees {torch.cuda.device_count()} CUDA devices here")
    return device


def pytest_collection_modifyitems(items) -> None:
    """Every test that takes ``device`` is marked ``on_device``, so that ``-m on_device`` runs them all (where
    ``NERFEXP_TEST_DEVICE`` names a GPU) and a new one needs no list kept by hand."""
    for item in items:
        if "device" in getattr(item, "fixturenames", ()):
            item.add_marker(ON_DEVICE)


@pytest.fixture(autouse=True)
def no_downloads(monkeypatch):
    """No test downloads AlexNet's weights (LPIPS fetches them where they are missing, ``fetch_alexnet``): its
    address is one where nothing listens, and HTTPS goes through a proxy that is not there (``NO_INTERNET``,
    also the environment of the commands ``run_nerfexp`` starts as processes). The download tests serve their
    own files on 127.0.0.1 (``tests.scoring.weights_server``)."""
    monkeypatch.setattr(perceptual, "ALEXNET_URL", refused_url(perceptual.ALEXNET_FILE))
    for name, value in NO_INTERNET.items():
        monkeypatch.setenv(name, value)


@pytest.fixture
def device() -> torch.device:
    """The device of a device-independent test (``NERFEXP_TEST_DEVICE``, the CPU where unset): the test builds its
    inputs and modules there, and compares against its truth (float64 references, closed forms) on the CPU."""
    return chosen_device()


@pytest.fixture
def tiny():
    return list(TINY)


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory) -> Path:
    """A finished run of the TINY config (60 steps, validation and a checkpoint every 30), trained once
    for every test that reads a run back (render, evaluation, resume); tests add files, never change it."""
    run_dir = tmp_path_factory.mktemp("tiny_run")
    result = run_nerfexp(*TINY, f"hydra.run.dir={run_dir}", cwd=run_dir)
    assert result.returncode == 0, result.stderr[-3000:]
    return run_dir
