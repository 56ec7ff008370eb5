"""Benchmark a run on a busy machine: the same short training alone, then beside N single-threaded busy processes
(pure-Python spin loops this script starts and kills), each with torch threads = 2, = 1 and auto (``threads``,
docs/acceleration.md), to measure what oversubscribed OpenMP threads cost and what the automatic choice gives;
then, with threads 2 and auto, neighbours that arrive ``--change-after`` seconds into the run and stay, and
neighbours there at its start that leave after as long (auto follows the machine while it trains:
``thread_changes``).

Each case runs ``nerfexp`` in its own process (``OMP_NUM_THREADS`` removed, so that auto is nerfexp's own
choice) and reads back its results.json: rays per second, training seconds, the run's CPU seconds, the others'
load (other processes' mean busy CPUs while it trained, ``nerfexp.machine_share``) and the threads it ran
with. Writes ``benchmarks/results/busy_machine.json`` and ``.md`` (``--out`` elsewhere), with the CPU model. Run it
alone on the machine: the "alone" cases must be.

    python benchmarks/threads/busy_machine.py                       # 300 steps, 2 busy processes, threads 2, 1, auto
    python benchmarks/threads/busy_machine.py --change-after 0      # without the arriving and leaving neighbours
    python benchmarks/threads/busy_machine.py --no-steady           # only those
    python benchmarks/threads/busy_machine.py --steps 10 --out /tmp/busy   # a smoke run
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from nerfexp.files import atomic_write
from nerfexp.machine_share import available_cpus
from nerfexp.rundir.layout import cpu_model

RESULTS = Path(__file__).parents[1] / "results"  # benchmarks/results
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


def train(threads: str, steps: int, extra: list[str], at_s: float | None = None,
          change=lambda: None) -> dict:
    """One short run with ``threads`` ("auto": nerfexp's choice); what its results.json says of its speed.
    ``change`` is called ``at_s`` seconds after the run's process starts (None: never)."""
    env = {key: value for key, value in os.environ.items() if key != "OMP_NUM_THREADS"}
    with tempfile.TemporaryDirectory() as tmp:
        overrides = [f"scale.steps={steps}", f"scale.val_every={steps}", "trainer.enable_progress_bar=false",
                     *([] if threads == "auto" else [f"threads={threads}"]), *extra, f"hydra.run.dir={tmp}"]
        exe = Path(sys.executable).with_name("nerfexp")
        timer = threading.Timer(at_s, change) if at_s is not None else None
        process = subprocess.Popen([str(exe), *overrides], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                   text=True)
        if timer is not None:
            timer.start()
        _, stderr = process.communicate()
        if timer is not None:
            timer.cancel()
        if process.returncode != 0:
            raise SystemExit(f"nerfexp {' '.join(overrides)} failed:\n{stderr[-2000:]}")
        results = json.loads((Path(tmp) / "results.json").read_text())
    return {key: results.get(key) for key in ("rays_per_s", "train_time_s", "cpu_time_s", "other_load",
                                              "torch_threads", "thread_changes", "kernel_build_s", "test_psnr")}


def changing(busy: int, threads: str, steps: int, extra: list[str], after_s: float, arrive: bool) -> dict:
    """A run with ``threads`` whose ``busy`` neighbours arrive ``after_s`` seconds into it and stay (``arrive``),
    or are there at its start and leave after as long."""
    others = [] if arrive else spinners(busy)
    try:
        time.sleep(0 if arrive else SETTLE_S)
        change = (lambda: others.extend(spinners(busy))) if arrive else (lambda: stop(others))
        return train(threads, steps, extra, after_s, change)
    finally:
        stop(others)


def changes_text(changes: list[dict] | None) -> str:
    """``thread_changes`` as ``step: threads, ...`` ("–": none, or not recorded)."""
    return ", ".join(f"{c['step']}: {c['threads']}" for c in changes) if changes else "–"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--busy", type=int, default=2, help="single-threaded busy processes beside the run")
    parser.add_argument("--threads", nargs="+", default=["2", "1", "auto"])
    parser.add_argument("--change-after", type=float, default=20.0,
                        help="seconds into a run at which the neighbours arrive (or leave); 0: no such cases")
    parser.add_argument("--steady", action=argparse.BooleanOptionalAction, default=True,
                        help="the cases alone and beside neighbours there all along (--no-steady: leave them out)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("overrides", nargs="*", help="more overrides for every run (e.g. encoding=hashgrid)")
    args = parser.parse_args()
    try:
        cpu = cpu_model(Path("/proc/cpuinfo").read_text())
    except OSError:
        cpu = "CPU"
    cases = []
    for busy in (0, args.busy) if args.steady else ():
        for threads in args.threads:
            others = spinners(busy)
            try:
                time.sleep(SETTLE_S if busy else 0)
                measured = train(threads, args.steps, args.overrides)
            finally:
                stop(others)
            cases.append({"busy_processes": busy, "threads": threads, **measured})
            print(json.dumps(cases[-1]), flush=True)
    for arrive in (True, False) if args.change_after > 0 else ():
        for threads in ("2", "auto"):
            measured = changing(args.busy, threads, args.steps, args.overrides, args.change_after, arrive)
            when = f"{'arrive' if arrive else 'leave'} after {args.change_after:.0f} s"
            cases.append({"busy_processes": f"{args.busy}, {when}", "threads": threads, **measured})
            print(json.dumps(cases[-1]), flush=True)
    report = {"cpu": cpu, "cpus": available_cpus(), "steps": args.steps, "overrides": args.overrides, "cases": cases}
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write(args.out / "busy_machine.json", (json.dumps(report, indent=2) + "\n").encode())

    def cell(value, digits: int) -> str:
        return "–" if value is None else f"{value:.{digits}f}"

    lines = [f"CPU: {cpu}, {available_cpus()} CPUs this process may use; {args.steps} steps"
             f"{', ' + ' '.join(args.overrides) if args.overrides else ''}.", "",
             "| busy processes | threads (asked) | torch threads | rays / s | train s | CPU s | others' load (CPUs) "
             "| thread changes (step: threads) |",
             "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {c['busy_processes']} | {c['threads']} | {c['torch_threads']} | {cell(c['rays_per_s'], 0)} | "
              f"{cell(c['train_time_s'], 1)} | {cell(c['cpu_time_s'], 1)} | {cell(c['other_load'], 2)} | "
              f"{changes_text(c.get('thread_changes'))} |" for c in cases]
    atomic_write(args.out / "busy_machine.md", ("\n".join(lines) + "\n").encode())
    print("\n".join(lines))


if __name__ == "__main__":
    main()
