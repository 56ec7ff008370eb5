"""What the scene contraction buys on ground truth: the built-in still life inside a painted room ten times the
cameras' distance away (``nerfexp-scene --scene unbounded --format nerfstudio``), trained three ways.

    python benchmarks/unbounded.py [--resolution 48] [--steps 1500] [--seeds 0 1 2] [--far 200]

- ``bounded``: ``contraction=none`` with the scene format's far (twice the cameras' bound): the room lies beyond it,
  so the renderer's white background stands in for it (a bounded NeRF on an unbounded scene);
- ``far``: ``contraction=none data.far=FAR``: samples spaced evenly out to the room and past it;
- ``contracted``: ``contraction=mipnerf360``: positions contracted, samples evenly in disparity beyond the
  cameras' ball, out to the contraction's own far (1000 radii of the ball).

Each with the default model at ``scale=cpu``, the given steps and seeds, one process at a time. Writes
``docs/results/unbounded.md`` and ``.json``: test PSNR and SSIM per run, their means, the differences to
``contracted`` paired by seed with their 95% intervals (``nerfexp.report.comparison``), a picture of one test
view, the CPU model and the command. Times are those of the runs as they ran (``train_time_s``): compare them
only where the script ran alone on the machine.
"""

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

from precision import cpu_model  # benchmarks/precision.py: the CPU's model name
from sheets import side_by_side  # benchmarks/sheets.py

from nerfexp.files import atomic_write
from nerfexp.report.comparison import paired_difference
from nerfexp.rundir.layout import machine

RESULTS = Path(__file__).parents[1] / "docs" / "results"
VARIANTS = ("bounded", "far", "contracted")


def overrides(variant: str, far: float) -> list[str]:
    return {"bounded": ["contraction=none"], "far": ["contraction=none", f"data.far={far:g}"],
            "contracted": ["contraction=mipnerf360"]}[variant]


def picture(out: Path, seed: int, view: int = 2) -> None:
    """Test view ``view`` as the three variants render it and its truth, side by side, 3 times enlarged:
    ``docs/results/unbounded.png``."""
    runs = [out / f"{variant}_{seed}" / "test" for variant in VARIANTS]
    paths = [run / f"r_{view}.png" for run in runs] + [runs[0] / f"r_{view}_target.png"]
    side_by_side(paths, RESULTS / "unbounded.png")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("unbounded_runs"))
    parser.add_argument("--resolution", type=int, default=48)
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--far", type=float, default=200.0)
    args = parser.parse_args()
    bin_dir = Path(sys.executable).parent
    scene = args.out / "scene"
    if not (scene / "transforms.json").is_file():
        subprocess.run([str(bin_dir / "nerfexp-scene"), str(scene), "--scene", "unbounded", "--format", "nerfstudio",
                        "--resolution", str(args.resolution), "--n-train", "100", "--n-val", "2", "--n-test", "10"],
                       check=True, stdout=subprocess.DEVNULL)
    runs = []
    for variant in VARIANTS:
        for seed in args.seeds:
            run_dir = args.out / f"{variant}_{seed}"
            if not (run_dir / "results.json").is_file():
                command = [str(bin_dir / "nerfexp"), "data=nerfstudio", f"data.root={scene}", "scale=cpu",
                           f"scale.steps={args.steps}", f"scale.val_every={args.steps}", f"seed={seed}",
                           *overrides(variant, args.far), "model.lpips=false", "trainer.enable_progress_bar=false",
                           f"hydra.run.dir={run_dir}"]
                print(" ".join(command[1:]), flush=True)
                with open(args.out / f"{run_dir.name}.log", "w") as log:
                    subprocess.run(command, check=True, stdout=log, stderr=subprocess.STDOUT)
            result = json.loads((run_dir / "results.json").read_text())
            runs.append({"variant": variant, "seed": seed, "test_psnr": result["test_psnr"],
                         "test_ssim": result["test_ssim"], "train_time_s": result["train_time_s"],
                         "evaluations_per_ray": result.get("evaluations_per_ray")})
    by = {v: {run["seed"]: run for run in runs if run["variant"] == v} for v in VARIANTS}
    means = {v: {key: statistics.mean(run[key] for run in by[v].values())
                 for key in ("test_psnr", "test_ssim", "train_time_s")} for v in VARIANTS}
    gains = {}
    for v in VARIANTS[:-1]:
        for key in ("test_psnr", "test_ssim"):
            contracted = {s: r[key] for s, r in by["contracted"].items()}
            d = paired_difference(contracted, {s: r[key] for s, r in by[v].items()})
            gains[f"{key} contracted - {v}"] = {"mean": d.mean, "n": d.n, "interval": d.interval, "verdict": d.verdict}
    record = {"command": "python " + " ".join(sys.argv), "machine": machine(), "cpu": cpu_model(),
              "resolution": args.resolution, "steps": args.steps, "seeds": args.seeds, "far": args.far,
              "runs": runs, "means": means, "contracted_minus": gains}
    atomic_write(RESULTS / "unbounded.json", json.dumps(record, indent=2).encode())
    picture(args.out, args.seeds[0])

    def interval(g: dict) -> str:
        low, high = g["interval"] if g["interval"] else (float("nan"), float("nan"))
        return f"{g['mean']:+.2f} [{low:+.2f}, {high:+.2f}] ({g['verdict']})"

    rows = [f"| {v} | {' '.join(overrides(v, args.far))} | {m['test_psnr']:.2f} | {m['test_ssim']:.4f} | "
            f"{m['train_time_s']:.0f} |" for v, m in means.items()]
    text = "\n".join([
        "# Unbounded scenes on ground truth: what the contraction buys", "",
        f"`{record['command']}` on {record['cpu']} ({record['machine']['device']}): the built-in still life inside "
        f"a room 10 times the cameras' distance away (`nerfexp-scene --scene unbounded`, {args.resolution} x "
        f"{args.resolution}, 100 training and 10 test views, every pixel opaque), the default model at `scale=cpu` "
        f"for {args.steps} steps, seeds {args.seeds}; means over seeds (each run in `unbounded.json`).", "",
        "| variant | overrides | test PSNR (dB) | test SSIM | train time (s) |", "|---|---|---|---|---|", *rows, "",
        "Contracted minus the others, paired by seed, with 95% t-intervals:", "",
        *[f"- {key}: {interval(g)}" for key, g in gains.items()], "",
        f"![test view 2: bounded, far, contracted (seed {args.seeds[0]}), and the truth](unbounded.png)", "",
    ])
    atomic_write(RESULTS / "unbounded.md", text.encode())
    print(text)


if __name__ == "__main__":
    main()
