"""Helpers shared by the tests: the real config shrunk to run in seconds, and the console scripts run
as a user runs them."""

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import lightning as L
import torch

from nerfexp.geometry.cameras import look_at

REPO = Path(__file__).parents[1]  # on the console scripts' PYTHONPATH: they can load callbacks from here

# Overrides that shrink the default experiment: a tiny network on a small version of the built-in scene
# (hierarchical: a single run refuses scale.n_single, which it would not use; TINY_SINGLE adds it).
TINY = [
    "scale.steps=60", "scale.val_every=30", "scale.batch_rays=256", "scale.depth=2", "scale.width=32",
    "scale.skips=[1]", "scale.view_hidden=16", "scale.n_coarse=16", "scale.n_fine=16",
    "scale.image_size=24", "data.n_train=12", "data.n_val=1", "data.n_test=2", "trainer.enable_progress_bar=false",
]
TINY_SINGLE = "scale.n_single=48"  # hierarchical=false: as many evaluations per ray as 16 + (16 + 16)


def command(script: str, *args: str) -> tuple[list[str], dict]:
    """The command line of a console script and the environment to run it in as a user would."""
    pythonpath = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))
    env = {**os.environ, "HYDRA_FULL_ERROR": "0", "PYTHONWARNINGS": "ignore", "PYTHONPATH": pythonpath}
    return [str(Path(sys.executable).with_name(script)), *args], env


def run_nerfexp(*args: str, cwd: Path, script: str = "nerfexp") -> subprocess.CompletedProcess:
    """Run a console script as a user would; ``cwd`` receives anything written to relative paths."""
    argv, env = command(script, *args)
    return subprocess.run(argv, cwd=cwd, capture_output=True, text=True, env=env, timeout=900)


def start_nerfexp(*args: str, cwd: Path) -> subprocess.Popen:
    """Start ``nerfexp`` as ``run_nerfexp`` runs it, without waiting for it (stdout and stderr: pipes)."""
    argv, env = command("nerfexp", *args)
    return subprocess.Popen(argv, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def read_json(path: Path) -> dict:
    return json.loads(path.read_text())


class KillAtStep(L.Callback):
    """Kills its own process with SIGKILL (no clean-up, as a preempted or out-of-memory job dies) when
    training is about to take step ``step + 1``: after the checkpoint and validation of step ``step``.
    Injected from the command line by ``kill_at(step)``."""

    def __init__(self, step: int):
        self.step = step

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.global_step == self.step:
            os.kill(os.getpid(), signal.SIGKILL)


def kill_at(step: int) -> list[str]:
    """Overrides that make a ``nerfexp`` run kill itself after step ``step`` (``KillAtStep``)."""
    return ["+callbacks.kill._target_=tests.helpers.KillAtStep", f"+callbacks.kill.step={step}"]


class NanTargets(L.Callback):
    """Makes the target colours of the first training batch NaN (as a damaged image could), so that the
    step's losses are NaN while every setting and weight is finite. Injected by ``nan_targets()``."""

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.global_step == 0:
            batch["rgb"].fill_(float("nan"))


def nan_targets() -> list[str]:
    """Overrides that make a ``nerfexp`` run's first batch have NaN targets (``NanTargets``)."""
    return ["+callbacks.nan._target_=tests.helpers.NanTargets"]


def final_state(run_dir: Path) -> dict:
    """What a run's last checkpoint holds: its step, learning rate, weights and Adam state."""
    checkpoint = torch.load(run_dir / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    return {"step": checkpoint["global_step"], "lr": checkpoint["optimizer_states"][0]["param_groups"][0]["lr"],
            "weights": checkpoint["state_dict"], "adam": checkpoint["optimizer_states"][0]["state"]}


def cameras_at(distance: list[float], elevation_deg: list[float], azimuth_deg: list[float]) -> torch.Tensor:
    """Cameras [N, 4, 4] at the given spherical coordinates (z up), looking at the origin."""
    r, e, a = (torch.tensor(v, dtype=torch.float64) for v in (distance, elevation_deg, azimuth_deg))
    e, a = torch.deg2rad(e), torch.deg2rad(a)
    eye = r[:, None] * torch.stack([e.cos() * a.cos(), e.cos() * a.sin(), e.sin()], -1)
    return look_at(eye, torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
