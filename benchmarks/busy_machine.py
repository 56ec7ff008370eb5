"""Benchmark a run on a busy machine: the same short training alone, then beside N single-threaded busy processes
(pure-Python spin loops this script starts and kills), each with torch threads = 2, = 1 and auto (``threads``,
docs/acceleration.md), to measure what oversubscribed OpenMP threads cost and what the automatic choice gives.

Each case runs ``nerfexp`` in its own process (``OMP_NUM_THREADS`` removed, so that auto is nerfexp's own
choice) and reads back its results.json: rays per second, training seconds, the run's CPU seconds, the others'
load (other processes' mean busy CPUs while it trained, ``nerfexp.training.machine_share``) and the threads it ran
with. Writes ``benchmarks/results/busy_machine.json`` and ``.md`` (``--out`` elsewhere), with the CPU model. Run it
alone on the machine: the "alone" cases must be.

    python benchmarks/busy_machine.py                       # 300 steps, 2 busy processes, threads 2, 1, auto
    python benchmarks/busy_machine.py --steps 10 --out /tmp/busy   # a smoke run
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from nerfexp.files import atomic_write
from nerfexp.rundir.layout import cpu_model
from nerfexp.training.machine_share import available_cpus

RESULTS = Path(__file__).parent / "results"
SPIN = "while True: pass"  # one busy CPU, single-threaded
SETTLE_S = 1.0  # seconds the busy processes run before a case starts


def spinners(n: int) -> list[subprocess.Popen]:
    """``n`` single-threaded busy processes, started now."""
    return [subprocess.Popen([sys.executable, "-c", SPIN]) for _ in range(n)]


def stop(processes: list[subprocess.Popen]) -> None:
    """Each of ``processes`` (this script's own) ended, by its id."""
    for process in processes:
        process.kill()
    for process in processes:
        process.wait()


def train(threads: str, steps: int, extra: list[str]) -> dict:
    """One short run with ``threads`` ("auto": nerfexp's choice); what its results.json says of its speed."""
    env = {key: value for key, value in os.environ.items() if key != "OMP_NUM_THREADS"}
    with tempfile.TemporaryDirectory() as tmp:
        overrides = [f"scale.steps={steps}", f"scale.val_every={steps}", "trainer.enable_progress_bar=false",
                     *([] if threads == "auto" else [f"threads={threads}"]), *extra, f"hydra.run.dir={tmp}"]
        exe = Path(sys.executable).with_name("nerfexp")
        done = subprocess.run([str(exe), *overrides], env=env, capture_output=True, text=True)
        if done.returncode != 0:
            raise SystemExit(f"nerfexp {' '.join(overrides)} failed:\n{done.stderr[-2000:]}")
        results = json.loads((Path(tmp) / "results.json").read_text())
    return {key: results.get(key) for key in ("rays_per_s", "train_time_s", "cpu_time_s", "other_load",
                                              "torch_threads", "kernel_build_s", "test_psnr")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--busy", type=int, default=2, help="single-threaded busy processes beside the run")
    parser.add_argument("--threads", nargs="+", default=["2", "1", "auto"])
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("overrides", nargs="*", help="more overrides for every run (e.g. encoding=hashgrid)")
    args = parser.parse_args()
    try:
        cpu = cpu_model(Path("/proc/cpuinfo").read_text())
    except OSError:
        cpu = "CPU"
    cases = []
    for busy in (0, args.busy):
        for threads in args.threads:
            others = spinners(busy)
            try:
                time.sleep(SETTLE_S if busy else 0)
                measured = train(threads, args.steps, args.overrides)
            finally:
                stop(others)
            cases.append({"busy_processes": busy, "threads": threads, **measured})
            print(json.dumps(cases[-1]), flush=True)
    report = {"cpu": cpu, "cpus": available_cpus(), "steps": args.steps, "overrides": args.overrides, "cases": cases}
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write(args.out / "busy_machine.json", (json.dumps(report, indent=2) + "\n").encode())

    def cell(value, digits: int) -> str:
        return "–" if value is None else f"{value:.{digits}f}"

    lines = [f"CPU: {cpu}, {available_cpus()} CPUs this process may use; {args.steps} steps"
             f"{', ' + ' '.join(args.overrides) if args.overrides else ''}.", "",
             "| busy processes | threads (asked) | torch threads | rays / s | train s | CPU s | others' load (CPUs) |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {c['busy_processes']} | {c['threads']} | {c['torch_threads']} | {cell(c['rays_per_s'], 0)} | "
              f"{cell(c['train_time_s'], 1)} | {cell(c['cpu_time_s'], 1)} | {cell(c['other_load'], 2)} |"
              for c in cases]
    atomic_write(args.out / "busy_machine.md", ("\n".join(lines) + "\n").encode())
    print("\n".join(lines))


if __name__ == "__main__":
    main()
