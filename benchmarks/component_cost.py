"""What each component for real photographs costs per training step: the default experiment with each of
``contraction=mipnerf360``, ``appearance=embedding`` and ``camera_opt=so3xr3`` on its own and all three, against
none, on the built-in scene, each run one process after the other (run it alone on the machine).

    python benchmarks/component_cost.py [--steps 300] [--out component_cost_runs]

Writes ``benchmarks/results/component_cost.md`` and ``.json``: per variant the seconds per training step
(``time_per_step_s`` of results.json: training alone, validation and test excluded), its ratio to the default's,
the network evaluations per ray, the whole run's wall-clock seconds (with the test, where NeRF-W's protocol fits
each test image's code), the CPU model and the command.
"""

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from precision import cpu_model  # benchmarks/precision.py: the CPU's model name

from nerfexp.files import atomic_write
from nerfexp.rundir.layout import machine

RESULTS = Path(__file__).parent / "results"
VARIANTS = {
    "default": [],
    "contraction": ["contraction=mipnerf360"],
    "appearance": ["appearance=embedding"],
    "camera_opt": ["camera_opt=so3xr3"],
    "all three": ["contraction=mipnerf360", "appearance=embedding", "camera_opt=so3xr3"],
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("component_cost_runs"))
    parser.add_argument("--steps", type=int, default=300)
    args = parser.parse_args()
    nerfexp = Path(sys.executable).with_name("nerfexp")
    rows = []
    for name, overrides in VARIANTS.items():
        run_dir = args.out / name.replace(" ", "_")
        command = [str(nerfexp), *overrides, f"scale.steps={args.steps}", f"scale.val_every={args.steps}",
                   "model.lpips=false", "trainer.enable_progress_bar=false", f"hydra.run.dir={run_dir}"]
        print(" ".join(command[1:]), flush=True)
        started = time.perf_counter()
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wall = time.perf_counter() - started
        result = json.loads((run_dir / "results.json").read_text())
        rows.append({"variant": name, "overrides": overrides, "time_per_step_s": result["time_per_step_s"],
                     "evaluations_per_ray": result["evaluations_per_ray"], "wall_s": wall,
                     "test_psnr": result["test_psnr"], "test_protocol": result["test_protocol"]})
    base = rows[0]["time_per_step_s"]
    record = {"command": "python " + " ".join(sys.argv), "machine": machine(), "cpu": cpu_model(),
              "steps": args.steps, "runs": rows}
    atomic_write(RESULTS / "component_cost.json", json.dumps(record, indent=2).encode())
    lines = [f"| {r['variant']} | `{' '.join(r['overrides']) or '(none)'}` | {r['time_per_step_s'] * 1000:.1f} | "
             f"{r['time_per_step_s'] / base:.2f} | {r['evaluations_per_ray']:.0f} | {r['wall_s']:.0f} |" for r in rows]
    text = "\n".join([
        "# What each component for real photographs costs per step", "",
        f"`{record['command']}` on {record['cpu']} ({record['machine']['device']}): the default experiment "
        f"(built-in scene, `scale=cpu`) for {args.steps} steps per variant, one process after the other.", "",
        "| variant | overrides | ms per training step | x default | evaluations per ray | run wall-clock (s) |",
        "|---|---|---|---|---|---|", *lines, "",
        "The wall-clock time includes the process's start, the validation and the test; with `appearance=embedding` "
        "the test fits each test image's code on its left half (NeRF-W's protocol).", "",
    ])
    atomic_write(RESULTS / "component_cost.md", text.encode())
    print(text)


if __name__ == "__main__":
    main()
