"""Shared fixtures: the real config, shrunk to run in seconds on a CPU."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

# Overrides that shrink the default experiment: a tiny network on a small version of the built-in scene.
TINY = [
    "scale.steps=60", "scale.val_every=30", "scale.batch_rays=256", "scale.depth=2", "scale.width=32",
    "scale.skips=[1]", "scale.view_hidden=16", "scale.n_coarse=16", "scale.n_fine=16", "scale.n_single=48",
    "scale.image_size=24", "data.n_train=12", "data.n_val=1", "data.n_test=2", "trainer.enable_progress_bar=false",
]


def run_nerfexp(*args: str, cwd: Path, script: str = "nerfexp") -> subprocess.CompletedProcess:
    """Run a console script as a user would; ``cwd`` receives anything written to relative paths."""
    exe = Path(sys.executable).with_name(script)
    env = {**os.environ, "HYDRA_FULL_ERROR": "0", "PYTHONWARNINGS": "ignore"}
    return subprocess.run([str(exe), *args], cwd=cwd, capture_output=True, text=True, env=env, timeout=900)


def read_json(path: Path) -> dict:
    return json.loads(path.read_text())


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
