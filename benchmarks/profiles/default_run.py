"""Benchmark the default experiment on this machine: wall time, throughput, memory, quality.

Runs ``nerfexp`` (the README's default, the complete model) and ``nerfexp encoding=none`` at the same
settings, each in its own process, and writes ``benchmarks/results/default_run.json`` and ``.md``:
wall time of the whole command, training steps per second, training rays and network samples per
second, the process's peak resident memory, and final test PSNR/SSIM.

    python benchmarks/profiles/default_run.py [extra overrides...]
"""

import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from nerfexp.files import atomic_write

RESULTS = Path(__file__).parents[1] / "results"  # benchmarks/results


def run(overrides: list[str]) -> dict:
    """Run one experiment in a child process; its own peak RSS comes from ``os.wait4``."""
    with tempfile.TemporaryDirectory() as tmp:
        exe = Path(sys.executable).with_name("nerfexp")
        start = time.perf_counter()
        child = subprocess.Popen([str(exe), *overrides, f"hydra.run.dir={tmp}", "trainer.enable_progress_bar=false"],
                                 stdout=subprocess.DEVNULL)
        _, status, usage = os.wait4(child.pid, 0)
        wall = time.perf_counter() - start
        if os.waitstatus_to_exitcode(status) != 0:
            raise SystemExit(f"nerfexp {' '.join(overrides)} failed")
        results = json.loads((Path(tmp) / "results.json").read_text())
    batch = results["config"]["datamodule"]["batch_rays"]
    steps_per_s = results["steps"] / results["train_time_s"]
    return {
        "overrides": overrides, "wall_time_s": round(wall, 1), "train_time_s": round(results["train_time_s"], 1),
        "steps": results["steps"], "steps_per_s": round(steps_per_s, 3),
        "train_rays_per_s": round(steps_per_s * batch, 1),
        "train_samples_per_s": round(steps_per_s * batch * results["evaluations_per_ray"], 1),
        "peak_rss_mib": round(usage.ru_maxrss / 1024, 1),  # ru_maxrss is in KiB on Linux
        "test_psnr": round(results["test_psnr"], 2), "test_ssim": round(results["test_ssim"], 4),
    }


def main() -> None:
    extra = sys.argv[1:]
    runs = {"complete": run(extra), "encoding=none": run(["encoding=none", *extra])}
    machine = {"cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
               "processor": platform.processor() or platform.machine(), "torch": torch.__version__,
               "cuda": torch.cuda.get_device_name() if torch.cuda.is_available() else None}
    gain = runs["complete"]["test_psnr"] - runs["encoding=none"]["test_psnr"]
    report = {"machine": machine, "runs": runs, "posenc_gain_db": round(gain, 2)}
    RESULTS.mkdir(exist_ok=True)
    atomic_write(RESULTS / "default_run.json", (json.dumps(report, indent=2) + "\n").encode())
    lines = ["| run | wall s | train s | steps/s | rays/s | samples/s | peak RSS MiB | test PSNR | test SSIM |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, r in runs.items():
        lines.append(f"| {name} | {r['wall_time_s']} | {r['train_time_s']} | {r['steps_per_s']} | "
                     f"{r['train_rays_per_s']:.0f} | {r['train_samples_per_s']:.0f} | {r['peak_rss_mib']} | "
                     f"{r['test_psnr']} | {r['test_ssim']} |")
    lines.append(f"\nPositional encoding gain: {gain:.2f} dB. Machine: {machine}.")
    atomic_write(RESULTS / "default_run.md", ("\n".join(lines) + "\n").encode())
    print("\n".join(lines))


if __name__ == "__main__":
    main()
