"""Where a real training step's time goes: seconds per step of Lightning's own loop on a composed config,
and the operators that take it.

Each variant (a set of overrides of ``nerfexp.conf``) trains with ``lightning.Trainer`` as a run does (its
precision, its optimizer, the grid's updates; no validation, no checkpoints, no logger) for ``--steps``
steps. Seconds per step: the wall-clock mean over the last ``--window`` steps (after the warm-up, the
occupancy grid's included); then ``--profile`` more steps under ``torch.profiler``, whose operators by
self time are listed (the profiler's own cost makes those steps slower: compare operators, not totals).
The variants run one after the other in this process, so that they share the machine's state. Each window also
records how many CPUs other processes kept busy meanwhile (``nerfexp.machine_share``: the system's CPU
counters against this process's own), and the record names the CPU (its model and timing units): a time says what
else ran and where.
On a GPU (the config's ``trainer.accelerator``: auto takes one where there is one; ``trainer.accelerator=gpu``
requires it) the clock waits for the GPU's queued work at both ends of the window, and the operators are
ranked by their kernels' device time.

Unlike ``benchmarks/kernels/precision.py`` (fixed inputs), the networks here see the batches of training: with
``acceleration=occupancy`` a packed batch of another size every step.

    python benchmarks/profiles/step_profile.py [--steps 1000] [--window 200] [--profile 20] [--threads N]
                                      [--variant NAME OVERRIDE ...]... [--out NAME_OR_PATH]

Default variants: the ``cpu_ablation`` sweep's complete model in float32 and in bf16. Writes
``benchmarks/results/NAME.{json,md}`` (NAME ``step_profile``; an absolute path writes PATH.json and PATH.md).
"""

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

import lightning as L
import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate
from torch.profiler import ProfilerActivity, profile

import nerfexp
from nerfexp import machine_share
from nerfexp.files import atomic_write
from nerfexp.rundir.layout import machine as machine_record
from nerfexp.training.callbacks import FlushDenormals
from nerfexp.training.precision import fill_precision

RESULTS = Path(__file__).parents[1] / "results"  # benchmarks/results
ABLATION = ["+sweeps=cpu_ablation", "ablation=complete", "seed=0"]
VARIANTS = {"cpu_ablation complete, float32": [*ABLATION, "trainer.precision=32-true"],
            "cpu_ablation complete, bf16": [*ABLATION, "trainer.precision=bf16-mixed"]}
TOP_OPS = 12


def synchronize(device: torch.device) -> None:
    """Wait for the work queued on ``device`` (a GPU's kernels run after the Python that launched them returns)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class StepClock(L.Callback):
    """Wall-clock seconds of the steps [start, stop), then ``profiled`` steps under torch.profiler (on a GPU,
    its operators by their kernels' device time)."""

    def __init__(self, start: int, stop: int, profiled: int):
        self.start, self.stop, self.profiled = start, stop, profiled
        self.step_s: float | None = None
        self.other_load: float | None = None  # CPUs other processes kept busy during the window, on average
        self._window_start: machine_share.Sample | None = None
        self.top_ops_ms: dict[str, float] = {}
        self._began = 0.0
        self._profiler = None

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.global_step in (self.start, self.stop):
            synchronize(pl_module.device)
            self._began = time.perf_counter()
        if trainer.global_step == self.start:
            self._window_start = machine_share.sample()
        if trainer.global_step == self.stop:
            cuda = pl_module.device.type == "cuda"
            self._profiler = profile(activities=[ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else []))
            self._profiler.__enter__()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if trainer.global_step == self.stop:
            synchronize(pl_module.device)
            self.step_s = (time.perf_counter() - self._began) / (self.stop - self.start)
            end = machine_share.sample()
            self.other_load = machine_share.other_load(machine_share.others_cpu_s(self._window_start, end),
                                                       end.wall_s - self._window_start.wall_s)
        elif trainer.global_step == self.stop + self.profiled:
            synchronize(pl_module.device)
            self._profiler.__exit__(None, None, None)
            time_of = "self_device_time_total" if pl_module.device.type == "cuda" else "self_cpu_time_total"
            events = sorted(self._profiler.key_averages(), key=lambda e: -getattr(e, time_of))[:TOP_OPS]
            self.top_ops_ms = {e.key: round(getattr(e, time_of) / 1e3 / self.profiled, 2) for e in events}


def measure(overrides: list[str], args) -> dict:
    """Seconds per step and the top operators of one variant."""
    with initialize_config_module("nerfexp.conf", version_base=None):
        cfg = compose("config", overrides=overrides)
    fill_precision(cfg)
    L.seed_everything(cfg.seed, verbose=False)
    model, datamodule = instantiate(cfg.model), instantiate(cfg.datamodule)
    clock = StepClock(args.steps - args.window, args.steps, args.profile)
    trainer = L.Trainer(accelerator=cfg.trainer.accelerator, devices=1, precision=cfg.trainer.precision,
                        max_steps=args.steps + args.profile, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0,
                        num_sanity_val_steps=0, callbacks=[FlushDenormals(), clock])
    trainer.fit(model, datamodule=datamodule)
    return {"overrides": overrides, "device": str(model.device), "precision": cfg.trainer.precision,
            "step_s": clock.step_s, "other_load": clock.other_load, "evaluations_per_ray": float(model.renderer.evaluations_per_ray),
            "top_ops_ms": clock.top_ops_ms}


def markdown(rows: dict, meta: dict) -> str:
    lines = [f"Seconds per training step (Lightning's loop, mean of steps {meta['steps'] - meta['window']} to "
             f"{meta['steps']}), then the operators by self time in {meta['profile']} profiled steps.", "",
             "| variant | device | precision | s / step | evaluations / ray | other processes' CPUs |",
             "|---|---|---|---|---|---|"]
    lines += [f"| {name} | {row['device']} | {row['precision']} | {row['step_s']:.4f} | "
              f"{row['evaluations_per_ray']:.1f} | {other_cpus(row.get('other_load'))} |" for name, row in rows.items()]
    for name, row in rows.items():
        lines += ["", f"{name} (`{' '.join(row['overrides'])}`), ms per profiled step "
                  f"({'device' if row['device'].startswith('cuda') else 'CPU'} self time):", "",
                  ", ".join(f"`{op}` {ms}" for op, ms in row["top_ops_ms"].items())]
    lines += ["", f"Command: `{meta['command']}`, the code measured (``nerfexp``) at commit {meta['commit']}.", "",
              f"Machine: {meta['machine']}."]
    return "\n".join(lines) + "\n"


def other_cpus(load: float | None) -> str:
    """How many CPUs other processes kept busy during a window, on average (``machine_share.other_load``)."""
    return "not measured" if load is None else f"{load:.2f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--window", type=int, default=200)
    parser.add_argument("--profile", type=int, default=20)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--variant", nargs="+", action="append", metavar=("NAME", "OVERRIDE"),
                        help="a name and its overrides; repeat for several (default: VARIANTS)")
    parser.add_argument("--out", default="step_profile")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    variants = {name: overrides for name, *overrides in args.variant} if args.variant else VARIANTS
    rows = {}
    for name, overrides in variants.items():
        rows[name] = measure(overrides, args)
        print(name, f"{rows[name]['step_s']:.4f} s/step", flush=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(nerfexp.__file__).parent).stdout.strip() if shutil.which("git") else ""
    meta = {"steps": args.steps, "window": args.window, "profile": args.profile, "commit": commit,
            "command": "python benchmarks/profiles/step_profile.py " + " ".join(sys.argv[1:]),
            "machine": {"device": machine_record()["device"], "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
                        "processor": platform.processor() or platform.machine(), "torch": torch.__version__,
                        "cuda": torch.version.cuda,
                        "gpu": torch.cuda.get_device_name() if torch.cuda.is_available() else None}}
    atomic_write(RESULTS / f"{args.out}.json", json.dumps({"meta": meta, "variants": rows}, indent=2).encode())
    atomic_write(RESULTS / f"{args.out}.md", markdown(rows, meta).encode())


if __name__ == "__main__":
    main()
