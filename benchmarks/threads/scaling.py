"""Training throughput against the number of processes: one and two CPU processes, and one GPU and
every GPU of the machine where there are GPUs.

Each setting is a real ``nerfexp`` run in its own process (``trainer=default`` for one process,
``trainer=ddp`` for several) at the same config, so the same global batch of ``scale.batch_rays`` rays per
step (strong scaling: n processes each render batch_rays / n rays). ``StepTimer`` (injected as a
callback) times the optimizer steps after a warm-up, with no validation inside the window; throughput is
batch_rays x timed steps / seconds. Writes ``benchmarks/results/scaling.json`` and ``.md``.

    python benchmarks/threads/scaling.py                      # CPU: 1 and 2 processes; GPUs: 1 and all
    python benchmarks/threads/scaling.py --steps 40 --warmup 10 --cpu-only   # a quick check
"""

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import lightning as L
import torch

from nerfexp.files import atomic_write

HERE = Path(__file__).parent  # on the child's PYTHONPATH: its callback is scaling.StepTimer
RESULTS = HERE.parent / "results"  # benchmarks/results
TIMER = "step_timer.json"

# The CPU setting: the default model (scale=cpu) with a batch big enough to split over two processes.
CPU = ["scale=cpu", "scale.batch_rays=1024", "data.n_val=1", "data.n_test=1", "trainer.accelerator=cpu"]
# The GPU setting: the paper's model, samples and batch (scale=paper) on the built-in scene at 100 x 100.
GPU = ["scale=paper", "scale.image_size=100", "data.n_val=1", "data.n_test=1", "trainer.accelerator=gpu"]


class StepTimer(L.Callback):
    """Times optimizer steps ``warmup`` to the last on every process; rank 0 writes ``step_timer.json``
    (steps, seconds) into the run directory. The steps of all ranks end together (DDP's gradient
    all-reduce synchronizes them), so rank 0's clock times the whole job."""

    def __init__(self, warmup: int):
        self.warmup, self._start, self._start_step = warmup, None, 0

    def _sync(self, trainer) -> None:
        if trainer.strategy.root_device.type == "cuda":
            torch.cuda.synchronize()

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.global_step == self.warmup and self._start is None:
            self._sync(trainer)
            self._start, self._start_step = time.perf_counter(), trainer.global_step

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if trainer.global_step == trainer.max_steps and self._start is not None and trainer.is_global_zero:
            self._sync(trainer)
            record = {"steps": trainer.global_step - self._start_step, "seconds": time.perf_counter() - self._start}
            atomic_write(Path(trainer.default_root_dir, TIMER), json.dumps(record).encode())


def run(overrides: list[str], steps: int, warmup: int) -> dict:
    """One timed run of ``nerfexp`` with ``overrides`` in a child process."""
    with tempfile.TemporaryDirectory() as tmp:
        exe = Path(sys.executable).with_name("nerfexp")
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")])}
        command = [str(exe), *overrides, f"scale.steps={steps}", f"scale.val_every={steps}",
                   "+callbacks.timer._target_=scaling.StepTimer", f"+callbacks.timer.warmup={warmup}",
                   f"hydra.run.dir={tmp}", "trainer.enable_progress_bar=false"]
        done = subprocess.run(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        if done.returncode != 0:
            raise SystemExit(f"nerfexp {' '.join(overrides)} failed:\n{done.stderr[-3000:]}")
        timer = json.loads((Path(tmp) / TIMER).read_text())
        results = json.loads((Path(tmp) / "results.json").read_text())
    batch = results["batch_rays"]
    return {"overrides": overrides, "processes": results["processes"], "batch_rays": batch,
            "timed_steps": timer["steps"], "seconds": round(timer["seconds"], 3),
            "rays_per_s": round(batch * timer["steps"] / timer["seconds"], 1),
            "test_psnr": round(results["test_psnr"], 2)}


def settings(cpu_only: bool) -> list[tuple[str, list[str]]]:
    """(name, overrides) of each setting to time on this machine."""
    runs = [("CPU, 1 process", [*CPU, "trainer=default"]),
            ("CPU, 2 processes (gloo)", [*CPU, "trainer=ddp", "trainer.devices=2"])]
    gpus = 0 if cpu_only else torch.cuda.device_count()
    if gpus:
        runs.append(("1 GPU", [*GPU, "trainer=default"]))
        runs += [(f"{n} GPUs (nccl)", [*GPU, "trainer=ddp", f"trainer.devices={n}"]) for n in sorted({2, gpus})
                 if n <= gpus]
    return runs


def machine() -> dict:
    return {"host": platform.node(), "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
            "processor": platform.processor() or platform.machine(), "torch": torch.__version__,
            "gpus": [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=300, help="optimizer steps per run")
    parser.add_argument("--warmup", type=int, default=50, help="steps left out of the timing")
    parser.add_argument("--cpu-only", action="store_true", help="leave out the GPUs")
    args = parser.parse_args()
    if not 0 <= args.warmup < args.steps:
        parser.error("--warmup must be below --steps")
    runs = {}
    for name, overrides in settings(args.cpu_only):
        runs[name] = run(overrides, args.steps, args.warmup)
        print(name, runs[name], flush=True)
    baseline = {"CPU": runs["CPU, 1 process"]["rays_per_s"], "GPU": runs.get("1 GPU", {}).get("rays_per_s")}
    for name, r in runs.items():
        r["speedup"] = round(r["rays_per_s"] / baseline["CPU" if name.startswith("CPU") else "GPU"], 2)
    report = {"machine": machine(), "steps": args.steps, "warmup": args.warmup, "runs": runs}
    RESULTS.mkdir(exist_ok=True)
    atomic_write(RESULTS / "scaling.json", (json.dumps(report, indent=2) + "\n").encode())
    lines = ["| setting | processes | global batch | timed steps | s | rays/s | speedup |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {name} | {r['processes']} | {r['batch_rays']} | {r['timed_steps']} | {r['seconds']} | "
              f"{r['rays_per_s']:.0f} | {r['speedup']}x |" for name, r in runs.items()]
    lines.append(f"\nMachine: {report['machine']}. Steps {args.steps}, the first {args.warmup} untimed.")
    atomic_write(RESULTS / "scaling.md", ("\n".join(lines) + "\n").encode())
    print("\n".join(lines))


if __name__ == "__main__":
    main()
