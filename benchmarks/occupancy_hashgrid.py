"""The occupancy grid with the hash grid against the positional encoding on the glossy scene, written as a
Blender-format dataset (its box is Blender's [-1.5, 1.5]^3, so the grid must learn what is empty): how
much each leaves out, why, and where a training step's time goes.

For each seed and each ``encoding`` (posenc, hashgrid), ``acceleration=occupancy`` trains with the real config
(``scale=cpu`` unless overridden, ``speed.train``): test PSNR, network evaluations per ray (the mean over
training) and seconds per step (validation excluded). Then the trained grid is read against the scene's true
geometry (``nerfexp.data.glossy``, analytic): the share of occupied cells among the cells whose centre lies
farther than half a cell's diagonal outside every object, near a surface, or inside one; the threshold the
grid used, min(sigma_t, mean estimate) (``OccupancyGrid.update``); each network's density at 100,000 random
points of the box at least 0.2 outside every object. Last, ``--profile-steps`` plain training steps of the
trained model with its own optimizer: the step's wall-clock time, its heaviest operators, the time of one
grid update, and the number of trained parameters.

Writes ``benchmarks/results/occupancy_hashgrid.{json,md}`` (``--out``):

    python benchmarks/occupancy_hashgrid.py --threads 2 [--steps 1500] [--seeds 0,1,2] [--scene DIR] [override ...]

Without ``--scene`` the glossy scene is written at 100 x 100 into a temporary folder (``nerfexp-scene DIR
--scene glossy``).
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

import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate
from speed import profile_step, train

from nerfexp.data import glossy
from nerfexp.files import atomic_write
from nerfexp.nerf.occupancy import OccupancyGrid, cell_corners, density_threshold

RESULTS = Path(__file__).parent / "results"
ENCODINGS = ("posenc", "hashgrid")
EMPTY_MARGIN = 0.2  # points at least this far outside every object count as empty space
N_EMPTY_POINTS = 100_000


def glossy_signed_distance(points: torch.Tensor) -> torch.Tensor:
    """The signed distance [...] of points [..., 3] (float64) to the glossy scene (negative inside): the
    smallest of the base's (a flat vertical cylinder), the mirror sphere's and the torus's."""
    (centre_xy, radius, bottom, top) = glossy.BASE
    radial = (points[..., :2] - points.new_tensor(centre_xy)).norm(dim=-1) - radius
    height = (points[..., 2] - (bottom + top) / 2).abs() - (top - bottom) / 2
    q = torch.stack([radial, height], -1)
    base = q.clamp_min(0).norm(dim=-1) + q.amax(-1).clamp_max(0)
    mirror = (points - points.new_tensor(glossy.MIRROR[0])).norm(dim=-1) - glossy.MIRROR[1]
    local = (points - points.new_tensor(glossy.TORUS_CENTRE)) @ glossy.torus_frame(glossy.TORUS_AXIS).T
    torus = glossy.torus_sdf(local, glossy.TORUS_MAJOR, glossy.TORUS_MINOR)
    return torch.stack([base, mirror, torus], -1).amin(-1)


def grid_report(grid: OccupancyGrid, density_fns: dict) -> dict:
    """The trained grid against the scene's geometry, and each network's density in empty space."""
    diagonal = float(grid.cell_size.norm())
    sigma_t = density_threshold(grid.threshold, diagonal)
    mean = float(grid.density.mean())
    centres = grid.aabb[0] + (cell_corners(grid.resolution) + 0.5) * grid.cell_size  # [R^3, 3]
    distance = glossy_signed_distance(centres.double()).float()
    kinds = {"outside": distance > diagonal / 2, "near_surface": distance.abs() <= diagonal / 2,
             "inside": distance < -diagonal / 2}
    cells = {kind: {"cells": int(mask.sum()), "occupied": int((grid.occupied & mask).sum()),
                    "median_estimate": float(grid.density[mask].median())} for kind, mask in kinds.items()}
    generator = torch.Generator().manual_seed(0)
    points = grid.aabb[0] + torch.rand(4 * N_EMPTY_POINTS, 3, generator=generator) * (grid.aabb[1] - grid.aabb[0])
    empty = points[glossy_signed_distance(points.double()) > EMPTY_MARGIN][:N_EMPTY_POINTS]
    quantiles = torch.tensor([0.5, 0.9, 0.99])
    in_empty_space = {}
    with torch.no_grad():
        for name, fn in density_fns.items():
            sigma = fn(empty)
            in_empty_space[name] = {**dict(zip(("median", "q90", "q99"), sigma.quantile(quantiles).tolist())),
                                    "share_above_sigma_t": float((sigma > sigma_t).float().mean())}
    return {"occupied_share": float(grid.occupied.float().mean()), "sigma_t": sigma_t, "mean_estimate": mean,
            "threshold_used": min(mean, sigma_t), "cells": cells, "density_in_empty_space": in_empty_space}


def run(cfg, datamodule, n_profile_steps: int) -> dict:
    model, result = train(cfg, datamodule)
    renderer = model.renderer
    result["optimizer"] = cfg.model.optimizer._target_
    result["grid"] = grid_report(renderer.grid, {"coarse": renderer.coarse.density, "fine": renderer.fine.density})
    result["n_parameters"] = sum(p.numel() for p in model.parameters())
    grid, start = renderer.grid, time.perf_counter()
    with torch.no_grad():
        for i in range(n_profile_steps):  # past the warm-up: a random quarter of the cells through both networks
            grid.update(grid.update_every * (grid.warmup_steps + 1 + i), renderer.density_fns())
    result["grid_update_s"] = (time.perf_counter() - start) / n_profile_steps
    result["profile"] = profile_step(model, datamodule, n_profile_steps, result["precision"])
    return result


def markdown(report: dict) -> str:
    lines = ["| seed | encoding | test PSNR | evals / ray | s / step | plain step ms | grid update ms | "
             "occupied cells | outside cells occupied | threshold used | parameters | optimizer |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in report["runs"]:
        g = r["grid"]
        outside = g["cells"]["outside"]
        lines.append(f"| {r['seed']} | {r['encoding']} | {r['test_psnr']:.2f} | {r['evaluations_per_ray']:.1f} | "
                     f"{r['s_per_step']:.3f} | {r['profile']['step_s'] * 1e3:.0f} | {r['grid_update_s'] * 1e3:.0f} | "
                     f"{g['occupied_share']:.1%} | {outside['occupied']} of {outside['cells']} | "
                     f"{g['threshold_used']:.4f} | {r['n_parameters']:,} | {r['optimizer'].rsplit('.', 1)[-1]} |")
    lines += ["", "Each network's density at points at least 0.2 outside every object (median, 99th percentile, "
              "share above sigma_t):", ""]
    for r in report["runs"]:
        parts = [f"{name} {d['median']:.2g} / {d['q99']:.2g} / {d['share_above_sigma_t']:.2%}"
                 for name, d in r["grid"]["density_in_empty_space"].items()]
        lines.append(f"- seed {r['seed']}, {r['encoding']}: " + "; ".join(parts))
    lines += ["", "Heaviest operators of a plain training step (ms per step):", ""]
    for r in report["runs"]:
        top = ", ".join(f"{k} {v}" for k, v in list(r["profile"]["top_ops_ms"].items())[:5])
        lines.append(f"- seed {r['seed']}, {r['encoding']}: {top}")
    lines += ["", f"Command: `{report['command']}`. Settings: {report['settings']}. Machine: {report['machine']}."]
    return "\n".join(lines) + "\n"


def write_glossy_scene(folder: Path) -> Path:
    subprocess.run([sys.executable, "-m", "nerfexp.commands.scene", str(folder), "--scene", "glossy"], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return folder


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--seeds", default="0", help="comma-separated")
    parser.add_argument("--scene", type=Path, default=None, help="the glossy scene's folder (default: written anew)")
    parser.add_argument("--profile-steps", type=int, default=10)
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("overrides", nargs="*", help="config overrides for every run")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    seeds = [int(s) for s in args.seeds.split(",")]
    runs = []
    with tempfile.TemporaryDirectory() as scratch:
        root = args.scene or write_glossy_scene(Path(scratch) / "glossy")
        overrides = ["data=blender", f"data.root={root}", "acceleration=occupancy", f"scale.steps={args.steps}",
                     f"scale.val_every={args.steps}", *args.overrides]
        datamodule = None
        for seed in seeds:
            for encoding in ENCODINGS:
                with initialize_config_module("nerfexp.conf", version_base=None):
                    cfg = compose("config", overrides=[*overrides, f"encoding={encoding}", f"seed={seed}"])
                datamodule = datamodule or instantiate(cfg.datamodule)  # the scene is loaded once
                result = {"seed": seed, "encoding": encoding, **run(cfg, datamodule, args.profile_steps)}
                runs.append(result)
                print({k: v for k, v in result.items() if k not in ("curve", "grid", "profile")}, flush=True)
    machine = {"cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
               "processor": platform.processor() or platform.machine(), "torch": torch.__version__,
               "cuda": torch.cuda.get_device_name() if torch.cuda.is_available() else None}
    report = {"command": " ".join(["python", "benchmarks/occupancy_hashgrid.py", *sys.argv[1:]]), "machine": machine,
              "settings": {"overrides": [o for o in overrides if not o.startswith("data.root=")], "seeds": seeds,
                           "profile_steps": args.profile_steps}, "runs": runs}
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write(args.out / "occupancy_hashgrid.json", (json.dumps(report, indent=2) + "\n").encode())
    atomic_write(args.out / "occupancy_hashgrid.md", markdown(report).encode())
    print(markdown(report))


if __name__ == "__main__":
    main()
