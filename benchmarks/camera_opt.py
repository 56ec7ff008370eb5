"""What camera refinement buys on ground truth: the built-in scene's training poses perturbed by known amounts
(``datamodule.pose_noise``), trained with and without ``camera_opt=so3xr3``, against training on the true poses,
and each scored with the test cameras as given and refined with the networks frozen (``test_cameras``).

    python benchmarks/camera_opt.py [--steps 1000] [--seeds 0 1 2] [--size 24] [--noise 2 0.02]

Variants (each x ``test_cameras=given,refined``): ``true`` (the true poses, ``camera_opt=off``), ``perturbed``
(perturbed poses, off), ``refined`` (perturbed poses, ``camera_opt=so3xr3`` with a 300-step warm-up). A small
model (2 layers of 32, 16 + 16 samples, 256 rays per batch, float32, ``scale.position_input_scale=0.125``), 16
training and 4 test views, one process at a time. Writes ``docs/results/camera_opt.json`` and the table
``camera_opt_table.md`` (included by ``camera_opt.md``): test PSNR means over seeds, the training poses' rotation
and centre errors before and after (``RUN_DIR/cameras/train_poses.json``), the share of the gap between perturbed
and true poses that refinement takes back, and the differences paired by seed with their 95% intervals
(``nerfexp.report.comparison``), the CPU model and the command.
"""

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

from precision import cpu_model  # benchmarks/precision.py: the CPU's model name

from nerfexp.files import atomic_write
from nerfexp.report.comparison import paired_difference
from nerfexp.rundir.layout import machine

RESULTS = Path(__file__).parents[1] / "docs" / "results"
SMALL = ["scale.batch_rays=256", "scale.depth=2", "scale.width=32", "scale.skips=[1]", "scale.view_hidden=16",
         "scale.n_coarse=16", "scale.n_fine=16", "data.n_train=16", "data.n_val=1", "data.n_test=4",
         "scale.position_input_scale=0.125", "trainer.precision=32-true", "logger=none", "model.lpips=false",
         "trainer.enable_progress_bar=false"]
VARIANTS = ("true", "perturbed", "refined")
TEST_CAMERAS = ("given", "refined")


def overrides(variant: str, noise: list[float]) -> list[str]:
    perturb = [f"datamodule.pose_noise=[{noise[0]:g},{noise[1]:g}]"]
    return {"true": ["camera_opt=off"], "perturbed": ["camera_opt=off", *perturb],
            "refined": ["camera_opt=so3xr3", "camera_opt.correction.warmup_steps=300", *perturb]}[variant]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("camera_opt_runs"))
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--size", type=int, default=24)
    parser.add_argument("--noise", type=float, nargs=2, default=[2.0, 0.02], metavar=("DEGREES", "FRACTION"))
    args = parser.parse_args()
    nerfexp = Path(sys.executable).with_name("nerfexp")
    args.out.mkdir(parents=True, exist_ok=True)
    runs = []
    for variant in VARIANTS:
        for test_cameras in TEST_CAMERAS:
            for seed in args.seeds:
                run_dir = args.out / f"{variant}_{test_cameras}_{seed}"
                if not (run_dir / "results.json").is_file():
                    command = [str(nerfexp), *overrides(variant, args.noise), f"test_cameras={test_cameras}", *SMALL,
                               f"scale.image_size={args.size}", f"scale.steps={args.steps}",
                               f"scale.val_every={args.steps}", f"seed={seed}", f"hydra.run.dir={run_dir}"]
                    print(" ".join(command[1:]), flush=True)
                    with open(args.out / f"{run_dir.name}.log", "w") as log:
                        subprocess.run(command, check=True, stdout=log, stderr=subprocess.STDOUT)
                result = json.loads((run_dir / "results.json").read_text())
                poses = run_dir / "cameras" / "train_poses.json"
                errors = json.loads(poses.read_text())["errors"] if poses.is_file() else None
                runs.append({"variant": variant, "test_cameras": test_cameras, "seed": seed,
                             "psnr": result["test_psnr"], "ssim": result["test_ssim"],
                             "test_camera_fit_deg": result.get("test_camera_fit_deg"),
                             "pose_errors": errors, "train_time_s": result["train_time_s"]})

    def psnrs(variant: str, test_cameras: str) -> dict[int, float]:
        return {r["seed"]: r["psnr"] for r in runs if r["variant"] == variant and r["test_cameras"] == test_cameras}

    rows, comparisons = [], {}
    for test_cameras in TEST_CAMERAS:
        means = {v: statistics.mean(psnrs(v, test_cameras).values()) for v in VARIANTS}
        gap = means["true"] - means["perturbed"]
        share = (means["refined"] - means["perturbed"]) / gap if gap > 0 else float("nan")
        rows.append(f"| {test_cameras} | {means['true']:.2f} | {means['perturbed']:.2f} | {means['refined']:.2f} | "
                    f"{share:.0%} |")
        for a, b in (("refined", "perturbed"), ("true", "refined"), ("true", "perturbed")):
            d = paired_difference(psnrs(a, test_cameras), psnrs(b, test_cameras))
            comparisons[f"{test_cameras}: {a} - {b}"] = {"mean": d.mean, "n": d.n, "interval": d.interval,
                                                         "verdict": d.verdict}
    refined_runs = [r for r in runs if r["variant"] == "refined" and r["pose_errors"]]
    before, after = ({k: statistics.mean(r["pose_errors"][when][k] for r in refined_runs)
                      for k in ("rotation_deg", "centre")} for when in ("before", "after"))
    record = {"command": "python " + " ".join(sys.argv), "machine": machine(), "cpu": cpu_model(),
              "steps": args.steps, "seeds": args.seeds, "size": args.size, "noise": args.noise, "runs": runs,
              "differences": comparisons, "pose_errors_before": before, "pose_errors_after": after}
    atomic_write(RESULTS / "camera_opt.json", json.dumps(record, indent=2).encode())

    def said(g: dict) -> str:
        low, high = g["interval"] if g["interval"] else (float("nan"), float("nan"))
        return f"{g['mean']:+.2f} dB [{low:+.2f}, {high:+.2f}] ({g['verdict']})"

    text = "\n".join([
        f"`{record['command']}` on {record['cpu']}: {args.size} x {args.size} images, {args.steps} steps, seeds "
        f"{args.seeds}, training poses perturbed by {args.noise[0]:g} degrees and {args.noise[1]:.0%} of the "
        "cameras' radius (each run in `camera_opt.json`). Test PSNR (dB), means over seeds; share: (refined - "
        "perturbed) / (true - perturbed).", "",
        "| test cameras | true poses | perturbed | perturbed, refined (`camera_opt=so3xr3`) | share of the gap |",
        "|---|---|---|---|---|", *rows, "",
        f"Training poses (means over the refined runs, after a similarity): rotation {before['rotation_deg']:.3f} -> "
        f"{after['rotation_deg']:.3f} deg, centre {before['centre']:.4f} -> {after['centre']:.4f} scene units.", "",
        "Differences paired by seed, 95% t-intervals:", "",
        *[f"- {key}: {said(g)}" for key, g in comparisons.items()], "",
    ])
    atomic_write(RESULTS / "camera_opt_table.md", text.encode())
    print(text)


if __name__ == "__main__":
    main()
