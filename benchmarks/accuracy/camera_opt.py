"""What camera refinement buys on ground truth: the built-in scene's training poses perturbed by known amounts
(``datamodule.pose_noise``), trained with and without ``camera_opt=so3xr3``, against training on the true poses,
and each scored with the test cameras as given and refined with the networks frozen (``test_cameras``).

    python benchmarks/accuracy/camera_opt.py [--steps 1000] [--seeds 0 1 2] [--size 24] [--noise 2 0.02]
    python benchmarks/accuracy/camera_opt.py --study schedules --model default --size 64 --steps 1500 --seeds 0 1 2

``--study gap`` (the default). Variants (each x ``test_cameras=given,refined``): ``true`` (the true poses,
``camera_opt=off``), ``perturbed`` (perturbed poses, off), ``refined`` (perturbed poses, ``camera_opt=so3xr3``
with a 300-step warm-up). Writes ``docs/results/camera_opt.json`` and the table ``camera_opt_table.md``
(included by ``camera_opt.md``): test PSNR means over seeds, the training poses' rotation and centre errors
before and after (``RUN_DIR/cameras/train_poses.json``), the share of the gap between perturbed and true poses
that refinement takes back, and the differences paired by seed with their 95% intervals
(``nerfexp.report.comparison``), the CPU model and the command.

``--study schedules``: what lets camera refinement earn its place where the training poses are off and the test
views exact (``test_cameras=given``), the literature's remedies one at a time against ``camera_opt=so3xr3`` as
configured (``SCHEDULES``): BARF's coarse-to-fine window over the positional encoding's frequencies
(``encoding.position.coarse_to_fine``), a warm-up of the corrections' learning rate
(``camera_opt.correction.warmup_steps``), both, and the corrections' learning rate 3x higher or lower; beside
the true and the perturbed poses without refinement. Writes
``camera_opt_schedules.json`` and ``camera_opt_schedules_table.md``: per variant the test PSNR's mean over
seeds, how many seeds collapsed, the training poses' rotation error after refinement, each variant paired by
seed against ``so3xr3`` as configured, and the best variant none of whose seeds collapsed: the candidate for
``conf/camera_opt/so3xr3.yaml``'s defaults. ``--variants`` runs some of them (``so3xr3`` among them); a run
already in ``--out`` is read back, not trained again, so a later call can add variants to the same table.

``--model small``: 2 layers of 32, 16 + 16 samples, 256 rays per batch, ``scale.position_input_scale=0.125``;
``--model default``: the default model at ``scale=cpu``'s sizes. Both in float32, 16 training and 4 test views,
one process at a time. Every run goes to its end (``callbacks.guard.on_collapse=warn``) and records whether it
rendered nothing (``results.json``'s ``collapse``). ``--results DIR`` writes the files elsewhere (a smoke run's).
"""

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

from nerfexp.files import atomic_write
from nerfexp.report.comparison import paired_difference
from nerfexp.rundir.layout import machine

DOCS_RESULTS = Path(__file__).parents[2] / "docs" / "results"
# every run: 16 training and 4 test views, float32; a run that renders nothing goes to its end and says so
EVERY_RUN = ["data.n_train=16", "data.n_val=1", "data.n_test=4", "trainer.precision=32-true", "logger=none",
         "model.lpips=false", "trainer.enable_progress_bar=false", "callbacks.guard.on_collapse=warn"]
MODELS = {
    "small": ["scale.batch_rays=256", "scale.depth=2", "scale.width=32", "scale.skips=[1]", "scale.view_hidden=16",
              "scale.n_coarse=16", "scale.n_fine=16", "scale.position_input_scale=0.125"],
    "default": [],  # scale=cpu's
}
VARIANTS = ("true", "perturbed", "refined")
TEST_CAMERAS = ("given", "refined")
# --study schedules: each variant's overrides beyond the perturbed poses; {warmup} is --warmup's steps
# every refinement variant spells out its window and warm-up (camera_opt=so3xr3's defaults are the best measured,
# window 0.5 and warm-up 300): "so3xr3" is camera refinement without either, what each remedy is paired against
PLAIN = ["camera_opt=so3xr3", "camera_opt.coarse_to_fine=0"]
SCHEDULES = {
    "true": ["camera_opt=off"],  # the true poses: no datamodule.pose_noise (run_schedules)
    "perturbed": ["camera_opt=off"],
    "so3xr3": [*PLAIN, "camera_opt.correction.warmup_steps=0"],
    "coarse_to_fine": ["camera_opt=so3xr3", "camera_opt.coarse_to_fine=0.5", "camera_opt.correction.warmup_steps=0"],
    "warmup": [*PLAIN, "camera_opt.correction.warmup_steps={warmup}"],
    "coarse_to_fine_warmup": ["camera_opt=so3xr3", "camera_opt.coarse_to_fine=0.5",
                              "camera_opt.correction.warmup_steps={warmup}"],
    "lr_3x": [*PLAIN, "camera_opt.correction.warmup_steps=0", "camera_opt.correction.lr=3e-3",
              "camera_opt.correction.lr_final=3e-5"],
    "lr_third": [*PLAIN, "camera_opt.correction.warmup_steps=0", "camera_opt.correction.lr=3.3e-4",
                 "camera_opt.correction.lr_final=3.3e-6"],
}
REFERENCE = "so3xr3"  # camera refinement as configured: what each schedule is paired against


def perturbed(noise: list[float]) -> str:
    return f"datamodule.pose_noise=[{noise[0]:g},{noise[1]:g}]"


def overrides(variant: str, noise: list[float]) -> list[str]:
    perturb = [perturbed(noise)]
    return {"true": ["camera_opt=off"], "perturbed": ["camera_opt=off", *perturb],
            "refined": ["camera_opt=so3xr3", "camera_opt.coarse_to_fine=0", "camera_opt.correction.warmup_steps=300",
                        *perturb]}[variant]


def train(run_dir: Path, variant_overrides: list[str], args: argparse.Namespace, seed: int) -> dict:
    """One run (trained unless ``run_dir`` holds its ``results.json`` already): what the studies read of it, the test
    scores, ``collapse``, the training poses' errors (``cameras/train_poses.json``, None without refinement)."""
    if not (run_dir / "results.json").is_file():
        command = [str(Path(sys.executable).with_name("nerfexp")), *variant_overrides, *MODELS[args.model], *EVERY_RUN,
                   f"scale.image_size={args.size}", f"scale.steps={args.steps}", f"scale.val_every={args.steps}",
                   f"seed={seed}", f"hydra.run.dir={run_dir}"]
        print(" ".join(command[1:]), flush=True)
        with open(args.out / f"{run_dir.name}.log", "w") as log:
            subprocess.run(command, check=True, stdout=log, stderr=subprocess.STDOUT)
    result = json.loads((run_dir / "results.json").read_text())
    poses = run_dir / "cameras" / "train_poses.json"
    errors = json.loads(poses.read_text())["errors"] if poses.is_file() else None
    return {"seed": seed, "psnr": result["test_psnr"], "ssim": result["test_ssim"],
            "collapse": result.get("collapse"), "test_camera_fit_deg": result.get("test_camera_fit_deg"),
            "pose_errors": errors, "train_time_s": result["train_time_s"]}


def said(g: dict) -> str:
    """A paired difference (``nerfexp.report.comparison.paired_difference``, as recorded) in words."""
    low, high = g["interval"] if g["interval"] else (float("nan"), float("nan"))
    return f"{g['mean']:+.2f} dB [{low:+.2f}, {high:+.2f}] ({g['verdict']})"


def difference(a: dict[int, float], b: dict[int, float]) -> dict:
    d = paired_difference(a, b)
    return {"mean": d.mean, "n": d.n, "interval": d.interval, "verdict": d.verdict}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--study", choices=("gap", "schedules"), default="gap")
    parser.add_argument("--model", choices=tuple(MODELS), default="small")
    parser.add_argument("--out", type=Path, default=Path("camera_opt_runs"))
    parser.add_argument("--results", type=Path, default=DOCS_RESULTS)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--size", type=int, default=24)
    parser.add_argument("--noise", type=float, nargs=2, default=[2.0, 0.02], metavar=("DEGREES", "FRACTION"))
    parser.add_argument("--warmup", type=int, default=300, help="--study schedules: the warm-up's steps")
    parser.add_argument("--variants", nargs="+", choices=tuple(SCHEDULES), default=list(SCHEDULES),
                        help=f"--study schedules: the variants to run (they must include {REFERENCE}); runs already "
                             "in --out are read, not trained again, so a later call can add variants")
    args = parser.parse_args()
    if REFERENCE not in args.variants:
        parser.error(f"--variants must include {REFERENCE}, the variant the others are paired against")
    args.out.mkdir(parents=True, exist_ok=True)
    (run_gap if args.study == "gap" else run_schedules)(args)


def run_gap(args: argparse.Namespace) -> None:
    """``--study gap`` (the module's docstring)."""
    runs = []
    for variant in VARIANTS:
        for test_cameras in TEST_CAMERAS:
            for seed in args.seeds:
                run_dir = args.out / f"{variant}_{test_cameras}_{seed}"
                run = train(run_dir, [*overrides(variant, args.noise), f"test_cameras={test_cameras}"], args, seed)
                runs.append({"variant": variant, "test_cameras": test_cameras, **run})

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
            comparisons[f"{test_cameras}: {a} - {b}"] = difference(psnrs(a, test_cameras), psnrs(b, test_cameras))
    refined_runs = [r for r in runs if r["variant"] == "refined" and r["pose_errors"]]
    before, after = ({k: statistics.mean(r["pose_errors"][when][k] for r in refined_runs)
                      for k in ("rotation_deg", "centre")} for when in ("before", "after"))
    record = {"command": "python " + " ".join(sys.argv), "machine": machine(),
              "steps": args.steps, "seeds": args.seeds, "size": args.size, "noise": args.noise, "runs": runs,
              "differences": comparisons, "pose_errors_before": before, "pose_errors_after": after}
    atomic_write(args.results / "camera_opt.json", json.dumps(record, indent=2).encode())

    text = "\n".join([
        f"`{record['command']}` on {record['machine']['device']}: {args.size} x {args.size} images, "
        f"{args.steps} steps, seeds {args.seeds}, training poses perturbed by {args.noise[0]:g} degrees and "
        f"{args.noise[1]:.0%} of the cameras' radius (each run in `camera_opt.json`). Test PSNR (dB), means over "
        "seeds; share: (refined - perturbed) / (true - perturbed).", "",
        "| test cameras | true poses | perturbed | perturbed, refined (`camera_opt=so3xr3`) | share of the gap |",
        "|---|---|---|---|---|", *rows, "",
        f"Training poses (means over the refined runs, after a similarity): rotation {before['rotation_deg']:.3f} -> "
        f"{after['rotation_deg']:.3f} deg, centre {before['centre']:.4f} -> {after['centre']:.4f} scene units.", "",
        "Differences paired by seed, 95% t-intervals:", "",
        *[f"- {key}: {said(g)}" for key, g in comparisons.items()], "",
    ])
    atomic_write(args.results / "camera_opt_table.md", text.encode())
    print(text)


def run_schedules(args: argparse.Namespace) -> None:
    """``--study schedules`` (the module's docstring)."""
    runs = []
    for variant in args.variants:
        chosen = [o.format(warmup=args.warmup) for o in SCHEDULES[variant]]
        noise = [] if variant == "true" else [perturbed(args.noise)]
        for seed in args.seeds:
            run_dir = args.out / f"schedules_{variant}_{seed}"
            run = train(run_dir, [*chosen, *noise, "test_cameras=given"], args, seed)
            runs.append({"variant": variant, "overrides": chosen, **run})

    def psnrs(variant: str) -> dict[int, float]:
        return {r["seed"]: r["psnr"] for r in runs if r["variant"] == variant}

    summary = {}
    for variant in args.variants:
        own = [r for r in runs if r["variant"] == variant]
        refined = [r["pose_errors"]["after"]["rotation_deg"] for r in own if r["pose_errors"]]
        summary[variant] = {"psnr": statistics.mean(psnrs(variant).values()),
                            "collapsed": sum(r["collapse"] is not None for r in own), "seeds": len(own),
                            "rotation_deg_after": statistics.mean(refined) if refined else None,
                            f"minus_{REFERENCE}": None if variant == REFERENCE else difference(
                                psnrs(variant), psnrs(REFERENCE))}
    candidates = [v for v in args.variants if v not in ("true", "perturbed") and not summary[v]["collapsed"]]
    best = max(candidates, key=lambda v: summary[v]["psnr"]) if candidates else None
    record = {"command": "python " + " ".join(sys.argv), "machine": machine(),
              "model": args.model, "steps": args.steps, "seeds": args.seeds, "size": args.size, "noise": args.noise,
              "warmup": args.warmup, "variants": {v: [o.format(warmup=args.warmup) for o in SCHEDULES[v]]
                                                  for v in args.variants},
              "runs": runs, "summary": summary, "best": best}
    atomic_write(args.results / "camera_opt_schedules.json", json.dumps(record, indent=2).encode())

    def row(variant: str) -> str:
        v = summary[variant]
        rotation = "" if v["rotation_deg_after"] is None else f"{v['rotation_deg_after']:.3f}"
        paired = "" if v[f"minus_{REFERENCE}"] is None else said(v[f"minus_{REFERENCE}"])
        return (f"| {variant} | {' '.join(record['variants'][variant])} | {v['psnr']:.2f} | {v['collapsed']} of "
                f"{v['seeds']} | {rotation} | {paired} |")

    text = "\n".join([
        f"`{record['command']}` on {record['machine']['device']}: the {args.model} model, "
        f"{args.size} x {args.size} images, {args.steps} steps, seeds {args.seeds}, training poses perturbed by "
        f"{args.noise[0]:g} degrees and {args.noise[1]:.0%} of the cameras' radius (but `true`), test cameras as "
        "given (each run in `camera_opt_schedules.json`). Test PSNR (dB), means over seeds; collapsed: seeds whose "
        "test views all rendered nothing; rotation: the training poses' error after refinement (degrees, after a "
        f"similarity); paired by seed against `{REFERENCE}` as configured, 95% t-intervals.", "",
        "| variant | overrides | test PSNR | collapsed | rotation | minus so3xr3 |",
        "|---|---|---|---|---|---|", *(row(v) for v in args.variants), "",
        f"Best refinement none of whose seeds collapsed: {best or 'none'}.", "",
    ])
    atomic_write(args.results / "camera_opt_schedules_table.md", text.encode())
    print(text)


if __name__ == "__main__":
    main()
