"""Where the occupancy grid's quality loss lives: trained runs' test views rendered through other grids.

    python benchmarks/grid/grid_renders.py --grid-runs RUN... --plain-runs RUN... [--points 16] [--out PATH]

A run trained with ``acceleration=occupancy`` (``--grid-runs``) is rendered through its own grid (its test score),
a grid rebuilt from its networks now (``--points`` jittered points per cell, the largest density of its networks,
the grid's own threshold rule), every cell of its box occupied (the networks evaluated everywhere inside the box,
nothing outside it), and no grid at all. A run trained without one (``--plain-runs``) is rendered as it was
trained and through a grid rebuilt from its networks (with the first grid run's grid settings and box). If the
grid-trained networks score as well through every cell of the box as through their grid, the cells the grid skipped
hold no density that training failed to remove; if the plain networks score as well through a grid as without,
skipping at render time costs nothing and the loss is made in training.

Test PSNR as runs score it (``nerfexp.scoring.metrics.psnr``, the mean over the test views). Writes PATH.json and
PATH.md (default ``benchmarks/results/grid_renders``).
"""

import argparse
import copy
import json
import sys
from pathlib import Path

import torch
from hydra.utils import instantiate

from nerfexp.denormals import set_flush_denormal_everywhere
from nerfexp.files import atomic_write
from nerfexp.nerf.occupancy import OccupancyGrid, cell_corners
from nerfexp.products.trained import load_run
from nerfexp.rundir.layout import machine
from nerfexp.scoring.metrics import psnr

RESULTS = Path(__file__).parents[1] / "results"  # benchmarks/results
CHUNK = 1 << 16  # points per density evaluation


@torch.no_grad()
def rebuilt(grid: OccupancyGrid, density_fns, points: int, generator: torch.Generator) -> OccupancyGrid:
    """A copy of ``grid`` whose estimates are the largest density of ``density_fns`` (positions [N, 3] -> sigma
    [N]) at ``points`` uniformly jittered points in each cell, occupied by the grid's rule (``mark_occupied``)."""
    fresh = copy.deepcopy(grid)
    corners = cell_corners(fresh.resolution, fresh.aabb.device)  # [R^3, 3]
    largest = torch.zeros(len(corners), device=corners.device)
    for _ in range(points):
        jitter = torch.rand(corners.shape, generator=generator).to(corners.device)
        positions = fresh.aabb[0] + (corners + jitter) * fresh.cell_size
        for start in range(0, len(positions), CHUNK):
            part = slice(start, start + CHUNK)
            for density in density_fns:
                largest[part] = torch.maximum(largest[part], density(positions[part]).float())
    fresh.density.copy_(largest)
    fresh.mark_occupied()
    return fresh


def every_cell(grid: OccupancyGrid) -> OccupancyGrid:
    """A copy of ``grid`` with every cell occupied: the networks evaluated everywhere inside its box."""
    full = copy.deepcopy(grid)
    full.occupied.fill_(True)
    return full


@torch.no_grad()
def mean_test_psnr(module, test_views) -> float:
    """The mean PSNR of ``module``'s renders of the ``test_views`` (a test dataloader's whole images)."""
    scores = [psnr(module.render_image(view["origins"], view["directions"], view.get("viewdirs"))["rgb"],
                   view["rgb"], view.get("mask")) for view in test_views]
    return sum(scores) / len(scores)


def rendered_through(module, test_views, grids: dict[str, OccupancyGrid | None]) -> dict[str, float]:
    """Test PSNR of ``module`` rendered through each of ``grids`` (None: no grid); its own grid put back."""
    own = module.renderer.grid
    scores = {}
    for name, grid in grids.items():
        module.renderer.grid = grid
        scores[name] = mean_test_psnr(module, test_views)
    module.renderer.grid = own
    return scores


def grid_run_row(run: Path, points: int, generator: torch.Generator) -> tuple[dict, OccupancyGrid]:
    """A grid-trained run's scores through its own grid, a rebuilt one, every cell and none; its grid."""
    trained = load_run(run)
    module, grid = trained.module, trained.module.renderer.grid
    if grid is None:
        raise SystemExit(f"{run}: trained without acceleration=occupancy; give it with --plain-runs")
    views = whole_test_views(trained.cfg)
    fresh = rebuilt(grid, module.renderer.density_fns(), points, generator)
    row = rendered_through(module, views, {"own grid": grid, "rebuilt grid": fresh, "every cell of the box":
                                           every_cell(grid), "no grid": None})
    row.update({"cells occupied, own": float(grid.occupied.float().mean()),
                "cells occupied, rebuilt": float(fresh.occupied.float().mean())})
    return row, grid


def plain_run_row(run: Path, grid: OccupancyGrid, points: int, generator: torch.Generator) -> dict:
    """A run trained without a grid: its scores as trained and through a grid (``grid``'s settings and box)
    rebuilt from its networks."""
    trained = load_run(run)
    module = trained.module
    if module.renderer.grid is not None:
        raise SystemExit(f"{run}: trained with acceleration=occupancy; give it with --grid-runs")
    fresh = rebuilt(grid, module.renderer.density_fns(), points, generator)
    row = rendered_through(module, whole_test_views(trained.cfg), {"no grid": None, "rebuilt grid": fresh})
    row["cells occupied, rebuilt"] = float(fresh.occupied.float().mean())
    return row


def whole_test_views(cfg) -> list[dict]:
    """The whole test images of a run's data (its datamodule's test loader), loaded once."""
    datamodule = instantiate(cfg.datamodule)
    datamodule.setup("test")
    return list(datamodule.test_dataloader())


def markdown(record: dict) -> str:
    """The record as a page: a table per kind of run, a row per run."""
    lines = [f"`{record['command']}` on {record['machine']['device']} ({record['points']} jittered points per cell "
             "for a rebuilt grid). Test PSNR (dB) of each run rendered through:", ""]
    for kind, rows in (("trained with the grid", record["grid_runs"]), ("trained without", record["plain_runs"])):
        if not rows:
            continue
        columns = list(next(iter(rows.values())))
        lines += [f"| run ({kind}) | " + " | ".join(columns) + " |", "|---" * (len(columns) + 1) + "|"]
        lines += [f"| {run} | " + " | ".join(f"{row[c]:.3f}" for c in columns) + " |" for run, row in rows.items()]
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--grid-runs", type=Path, nargs="+", required=True)
    parser.add_argument("--plain-runs", type=Path, nargs="*", default=[])
    parser.add_argument("--points", type=int, default=16)
    parser.add_argument("--out", type=Path, default=RESULTS / "grid_renders")
    args = parser.parse_args()
    set_flush_denormal_everywhere(True)
    generator = torch.Generator().manual_seed(0)
    grid_rows, grid = {}, None
    for run in args.grid_runs:
        grid_rows[run.name], own = grid_run_row(run, args.points, generator)
        grid = grid or own
        print(run.name, grid_rows[run.name], flush=True)
    plain_rows = {}
    for run in args.plain_runs:
        plain_rows[run.name] = plain_run_row(run, grid, args.points, generator)
        print(run.name, plain_rows[run.name], flush=True)
    record = {"command": "python " + " ".join(sys.argv), "points": args.points, "machine": machine(),
              "grid_runs": grid_rows, "plain_runs": plain_rows}
    atomic_write(args.out.with_suffix(".json"), json.dumps(record, indent=2).encode())
    atomic_write(args.out.with_suffix(".md"), markdown(record).encode())
    print(markdown(record))


if __name__ == "__main__":
    main()
