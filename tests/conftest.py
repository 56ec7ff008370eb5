"""Shared fixtures: the real config, shrunk to run in seconds on a CPU (``tests.helpers.TINY``), and no test
reaching the internet."""

from pathlib import Path

import pytest

from nerfexp.training import perceptual
from tests.helpers import NO_INTERNET, TINY, run_nerfexp
from tests.training.weights_server import refused_url


@pytest.fixture(autouse=True)
def no_downloads(monkeypatch):
    """No test downloads AlexNet's weights (LPIPS fetches them where they are missing, ``fetch_alexnet``): its
    address is one where nothing listens, and HTTPS goes through a proxy that is not there (``NO_INTERNET``,
    also the environment of the commands ``run_nerfexp`` starts as processes). The download tests serve their
    own files on 127.0.0.1 (``tests.training.weights_server``)."""
    monkeypatch.setattr(perceptual, "ALEXNET_URL", refused_url(perceptual.ALEXNET_FILE))
    for name, value in NO_INTERNET.items():
        monkeypatch.setenv(name, value)


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
