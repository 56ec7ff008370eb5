"""Shared fixtures: the real config, shrunk to run in seconds on a CPU (``tests.helpers.TINY``)."""

from pathlib import Path

import pytest

from tests.helpers import TINY, run_nerfexp


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
