"""What a nerfstudio capture's own ray bounds buy: ``data=nerfstudio`` trained with ``experiment=fast`` twice per
seed, with the old rule (near 0.05 x ``data.bound``, far 2 x ``data.bound``, set explicitly) and with the new
default (the capture's sparse points, else its ``aabb_scale`` box, else the old rule:
``nerfexp.data.nerfstudio``), test PSNR paired by seed.

    python benchmarks/capture_bounds.py --scene DIR [--steps 3000] [--seeds 0 1 2] [--max-side 240]
    python benchmarks/capture_bounds.py --export glossy --scene OUT_DIR [--resolution 100] ...

``--scene DIR``: a folder in nerfstudio's format (``transforms.json``). ``--export builtin|glossy`` first writes
the built-in still life or the glossy scene (``nerfexp-scene --format nerfstudio``) to ``DIR`` and gives it an
Instant-NGP box (``aabb_scale``, ``scale``, ``offset``) that holds the scene's objects with ``--box-margin``
around the ball of radius ``SCENE_RADIUS`` that holds them (``ngp_box_keys``), so that the new default bounds the rays by the box; a folder already exported
with the same settings is reused. Runs go to ``--out`` (a run already there is read back, not trained again),
one process at a time: run it alone on the machine. Writes ``benchmarks/results/capture_bounds_NAME.json`` and
``.md`` (NAME: the scene folder's name): per seed both PSNRs and their difference, the paired mean with its 95%
interval (``nerfexp.report.comparison``), the bounds each rule gave, the CPU model and the command.
"""

import argparse
import json
import subprocess
import sys
from pathlib import Path

import torch
from precision import cpu_model  # benchmarks/precision.py: the CPU's model name

from nerfexp.commands.scene import main as write_scene
from nerfexp.data import glossy, procedural
from nerfexp.data.nerfstudio import FAR_FACTOR, NEAR_FRACTION, NerfstudioScene
from nerfexp.files import atomic_write
from nerfexp.report.comparison import paired_difference
from nerfexp.rundir.layout import machine

RESULTS = Path(__file__).parent / "results"
EVERY_RUN = ["experiment=fast", "data=nerfstudio", "logger=none", "model.lpips=false",
             "trainer.enable_progress_bar=false", "callbacks.guard.on_collapse=warn"]
BOUND = 4.0  # data.bound's default: the old rule's near and far are fractions of it


def scene_box(name: str) -> torch.Tensor:
    """[2, 3] the cube around the ball that holds the exported scene's objects (its ``SCENE_RADIUS``)."""
    radius = {"builtin": procedural.SCENE_RADIUS, "glossy": glossy.SCENE_RADIUS}[name]
    return torch.tensor([[-radius] * 3, [radius] * 3], dtype=torch.float64)


def ngp_box_keys(box: torch.Tensor, margin: float) -> dict:
    """Instant-NGP's ``aabb_scale``, ``scale`` and ``offset`` whose cube holds ``box`` [2, 3] with ``margin``
    around it: ``ngp_box`` maps the cube back to centre ((0.5 - offset_z), (0.5 - offset_x), (0.5 - offset_y))
    / scale, half side aabb_scale / (2 scale); with aabb_scale 1, scale = 1 / (2 half) and offset =
    (0.5 - c_y scale, 0.5 - c_z scale, 0.5 - c_x scale)."""
    centre = box.mean(0)
    half = float((box[1] - box[0]).max()) / 2 + margin
    scale = 1 / (2 * half)
    offset = [0.5 - float(centre[1]) * scale, 0.5 - float(centre[2]) * scale, 0.5 - float(centre[0]) * scale]
    return {"aabb_scale": 1, "scale": scale, "offset": offset}


def export(args: argparse.Namespace) -> None:
    """Write ``--export``'s scene to ``--scene`` in nerfstudio's format with its Instant-NGP box."""
    settings = {"export": args.export, "resolution": args.resolution, "n_train": args.n_train,
                "box_margin": args.box_margin}
    marker = args.scene / "capture_bounds.json"
    if marker.is_file() and json.loads(marker.read_text()) == settings:
        return
    write_scene([str(args.scene), "--scene", args.export, "--format", "nerfstudio", "--resolution",
                 str(args.resolution), "--n-train", str(args.n_train), "--n-val", "2", "--n-test", "10"])
    transforms = args.scene / "transforms.json"
    content = json.loads(transforms.read_text())
    content.update(ngp_box_keys(scene_box(args.export), args.box_margin))
    atomic_write(transforms, json.dumps(content, indent=2).encode())
    marker.write_text(json.dumps(settings))


def train(run_dir: Path, rule: list[str], args: argparse.Namespace, seed: int) -> dict:
    """One run (trained unless ``run_dir`` holds its ``results.json``): its test PSNR, SSIM, near and far."""
    if not (run_dir / "results.json").is_file():
        command = [str(Path(sys.executable).with_name("nerfexp")), *EVERY_RUN, f"data.root={args.scene.resolve()}",
                   *rule, f"scale.steps={args.steps}", f"scale.val_every={args.steps}", f"seed={seed}",
                   f"hydra.run.dir={run_dir}"] + ([f"data.max_side={args.max_side}"] if args.max_side else [])
        print(" ".join(command[1:]), flush=True)
        with open(run_dir.with_suffix(".log"), "w") as log:
            subprocess.run(command, check=True, stdout=log, stderr=subprocess.STDOUT)
    result = json.loads((run_dir / "results.json").read_text())
    data = result["config"]["data"]
    return {"seed": seed, "psnr": result["test_psnr"], "ssim": result["test_ssim"], "near": data["near"],
            "far": data["far"], "bounds": result.get("bounds"), "train_time_s": result["train_time_s"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", type=Path, required=True, help="a nerfstudio folder (written with --export)")
    parser.add_argument("--export", choices=("builtin", "glossy"), help="write this scene to --scene first")
    parser.add_argument("--resolution", type=int, default=100, help="--export's image side (default 100)")
    parser.add_argument("--n-train", type=int, default=100, help="--export's training views (default 100)")
    parser.add_argument("--box-margin", type=float, default=0.1, help="--export's box beyond the objects' ball (0.1)")
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--max-side", type=int, default=None, help="data.max_side (default: the images' size)")
    parser.add_argument("--out", type=Path, default=None, help="runs (default: SCENE_capture_bounds_runs/)")
    parser.add_argument("--results", type=Path, default=RESULTS)
    args = parser.parse_args()
    if args.export:
        export(args)
    name = args.scene.resolve().name
    out = args.out or args.scene.resolve().with_name(f"{name}_capture_bounds_runs")
    out.mkdir(parents=True, exist_ok=True)
    rules = {"old": [f"data.near={NEAR_FRACTION * BOUND:g}", f"data.far={FAR_FACTOR * BOUND:g}"], "new": []}
    runs = {rule: [train(out / f"{rule}_seed{seed}", overrides, args, seed) for seed in args.seeds]
            for rule, overrides in rules.items()}
    psnr = {rule: {run["seed"]: run["psnr"] for run in rows} for rule, rows in runs.items()}
    d = paired_difference(psnr["new"], psnr["old"])
    command = "python benchmarks/capture_bounds.py " + " ".join(sys.argv[1:])
    found = NerfstudioScene(root=str(args.scene), max_side=args.max_side)
    record = {"scene": str(args.scene), "steps": args.steps, "seeds": args.seeds, "runs": runs,
              "new_minus_old": {"mean": d.mean, "n": d.n, "interval": d.interval, "verdict": d.verdict},
              "new_bounds": {"near_far": found.ray_bounds(), "rule": found.bounds_rule()},
              "cpu": cpu_model(), "machine": machine(), "command": command}
    args.results.mkdir(parents=True, exist_ok=True)
    atomic_write(args.results / f"capture_bounds_{name}.json", json.dumps(record, indent=2).encode())
    low, high = d.interval if d.interval else (float("nan"), float("nan"))
    lines = [f"# Ray bounds from the capture: {name}", "",
             f"`{command}` on {cpu_model()}; `experiment=fast`, {args.steps} steps, one run at a time.", "",
             f"New default: near {found.ray_bounds()[0]:.3f}, far {found.ray_bounds()[1]:.3f} "
             f"({found.bounds_rule()}); old rule: near {NEAR_FRACTION * BOUND:g}, far {FAR_FACTOR * BOUND:g}.", "",
             "| seed | old rule PSNR | new default PSNR | new - old |", "|---|---|---|---|"]
    for old, new in zip(runs["old"], runs["new"]):
        lines.append(f"| {old['seed']} | {old['psnr']:.2f} | {new['psnr']:.2f} | {new['psnr'] - old['psnr']:+.2f} |")
    lines += ["", f"Paired by seed: {d.mean:+.2f} dB [{low:+.2f}, {high:+.2f}] ({d.verdict}, 95% t-interval, "
              f"{d.n} seeds)."]
    atomic_write(args.results / f"capture_bounds_{name}.md", ("\n".join(lines) + "\n").encode())
    print("\n".join(lines))


if __name__ == "__main__":
    main()
