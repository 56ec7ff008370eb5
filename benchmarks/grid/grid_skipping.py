"""Why the occupancy grid skips less with the hash grid than with the positional encoding: both trained alike on
one scene (the glossy scene by default, ``acceleration=occupancy``, float32), then their grids and the samples
they let through compared.

    python benchmarks/grid/grid_skipping.py [--steps 1000] [--scene DIR] [--threads 2] [--out grid_skipping]

For each encoding: network evaluations per ray (training mean, and over a fixed batch of test rays now), the
share of cells occupied, the density limit the grid used (min(sigma_t, mean estimate): which of the two), how
many occupied cells are above sigma_t and how many only above the mean, and of the samples evaluated on the test
rays the share whose rendering weight is below 1e-4 (in occupied cells, but absorbing almost nothing: evaluations
a tighter grid would skip), with the quantiles of those samples' densities against sigma_t.
Writes ``benchmarks/results/OUT.{json,md}``.
"""

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import lightning as L
import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate

from nerfexp.data.rays import WholeImages
from nerfexp.files import atomic_write
from nerfexp.nerf.occupancy import cell_indices
from nerfexp.rundir.layout import machine
from nerfexp.training.callbacks import FlushDenormals

RESULTS = Path(__file__).parents[1] / "results"  # benchmarks/results
ENCODINGS = {"posenc": ["encoding=posenc"], "hashgrid": ["encoding=hashgrid"]}
WASTED = 1e-4  # a sample whose rendering weight is below this absorbs almost nothing


def train(overrides: list[str]):
    """A model trained as a run trains it (Lightning's loop, the grid's updates), without validation."""
    with initialize_config_module("nerfexp.conf", version_base=None):
        cfg = compose("config", overrides=overrides)
    L.seed_everything(cfg.seed, verbose=False)
    model, datamodule = instantiate(cfg.model), instantiate(cfg.datamodule)
    trainer = L.Trainer(accelerator="cpu", devices=1, precision=cfg.trainer.precision, max_steps=cfg.scale.steps,
                        logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, limit_val_batches=0, num_sanity_val_steps=0,
                        callbacks=[FlushDenormals()])
    trainer.fit(model, datamodule=datamodule)
    return model, datamodule


@torch.no_grad()
def grid_state(model, datamodule, n_rays: int) -> dict:
    """The grid's state and what the fine network's samples on ``n_rays`` test rays absorb."""
    model.eval()
    renderer, grid = model.renderer, model.renderer.grid
    sigma_t = float(grid.cell_thresholds())
    mean = float(grid.density.mean())
    occupied = grid.occupied
    images = WholeImages(datamodule.scene.views("test"), torch.ones(3))
    origins = torch.cat([images[n]["origins"].reshape(-1, 3) for n in range(len(images))])
    directions = torch.cat([images[n]["directions"].reshape(-1, 3) for n in range(len(images))])
    pick = torch.randperm(len(origins), generator=torch.Generator().manual_seed(0))[:n_rays]
    origins, directions = origins[pick].float(), directions[pick].float()
    fine = renderer(origins, directions, deterministic=True)["fine"]
    points = origins[:, None] + directions[:, None] * fine["t_starts"][..., None]  # where the fine samples lie
    keep = grid.occupied_at(points)  # the samples the networks evaluated (before early termination)
    weights = fine["weights"][keep]
    density = model.renderer.fine.density(points[keep]).float()
    wasted = weights < WASTED
    quantiles = torch.quantile(density[wasted], torch.tensor([0.5, 0.9, 0.99])) if wasted.any() else torch.zeros(3)
    _, inside = cell_indices(points, grid.aabb, grid.resolution)
    return {"occupied_share": float(occupied.float().mean()), "sigma_t": sigma_t, "mean_estimate": mean,
            "limit": "mean" if mean < sigma_t else "sigma_t",
            "cells_above_sigma_t": int((grid.density > sigma_t).sum()),
            "cells_occupied_only_by_the_mean": int(((grid.density > mean) & (grid.density <= sigma_t)).sum()),
            "evaluations_per_ray_training": float(renderer.evaluations_per_ray),
            "evaluations_per_ray_test": float(renderer.stats["samples_per_ray"]),
            "fine_samples_in_occupied_cells_per_ray": float(keep.sum()) / n_rays,
            "fine_samples_inside_box_per_ray": float(inside.sum()) / n_rays,
            "wasted_share": float(wasted.float().mean()),
            "wasted_density_quantiles_50_90_99": [float(q) for q in quantiles]}


def markdown(record: dict) -> str:
    rows = record["encodings"]
    keys = list(next(iter(rows.values())))
    lines = [f"`{record['command']}` on {record['machine']['device']}: each encoding trained {record['steps']} steps "
             f"from seed 0 with `{' '.join(record['overrides'])}`; samples of the fine network on {record['rays']} "
             "test rays.", "", "| | " + " | ".join(rows) + " |", "|---" * (len(rows) + 1) + "|"]
    for key in keys:
        cells = [f"{v:.4g}" if isinstance(v, float) else (", ".join(f"{x:.3g}" for x in v) if isinstance(v, list)
                 else str(v)) for v in (rows[name][key] for name in rows)]
        lines.append(f"| {key} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--rays", type=int, default=2048)
    parser.add_argument("--scene", type=Path, default=None, help="a Blender-format scene (default: the glossy one)")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--out", default="grid_skipping")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    scene = args.scene
    if scene is None:
        scene = Path(tempfile.mkdtemp()) / "glossy"
        subprocess.run([sys.executable, "-m", "nerfexp.commands.scene", str(scene), "--scene", "glossy",
                        "--resolution", "100"], check=True, stdout=subprocess.DEVNULL)
    overrides = ["data=blender", f"data.root={scene}", "acceleration=occupancy", "trainer.precision=32-true",
                 f"scale.steps={args.steps}", "model.lpips=false"]
    rows = {}
    for name, encoding in ENCODINGS.items():
        model, datamodule = train([*overrides, *encoding])
        rows[name] = grid_state(model, datamodule, args.rays)
        print(name, rows[name], flush=True)
    record = {"command": "python " + " ".join(sys.argv), "steps": args.steps, "rays": args.rays,
              "overrides": [o for o in overrides if not o.startswith("data.root")], "machine": machine(),
              "encodings": rows}
    atomic_write(RESULTS / f"{args.out}.json", json.dumps(record, indent=2).encode())
    atomic_write(RESULTS / f"{args.out}.md", markdown(record).encode())
    print(markdown(record))


if __name__ == "__main__":
    main()
