"""The occupancy grid's lookup (``OccupancyGrid.occupied_at``) per call, the fused kernel (occupancy_lookup.cpp)
against the torch path it replaces (``cell_indices``), at the sizes of a ``scale=cpu`` step: 256 rays of 24 coarse
samples and of 24 + 48 fine ones, on grids of 32^3 and 64^3 cells (a fifth occupied) over Blender's box, points in a
box a third larger. Both answers are checked equal first; each time is the median of ``--repeats`` timings of
``--calls`` calls, in one process, alone on the machine.

    python benchmarks/occupancy_lookup.py [--calls 300] [--repeats 5] [--out NAME_OR_PATH]

Writes ``benchmarks/results/NAME.{json,md}`` (NAME ``occupancy_lookup``; an absolute path writes PATH.json and
PATH.md), the CPU model beside the figures.
"""

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

from nerfexp.files import atomic_write
from nerfexp.nerf.occupancy import OccupancyGrid, cell_indices
from nerfexp.rundir.layout import machine

RESULTS = Path(__file__).parent / "results"
RAYS = 256
SAMPLES = {"coarse (24)": 24, "fine (24 + 48)": 72}


def seconds_per_call(lookup, points: torch.Tensor, calls: int, repeats: int) -> float:
    """The median over ``repeats`` of the mean seconds of ``calls`` calls of ``lookup(points)``."""
    for _ in range(10):  # warm-up
        lookup(points)
    timings = []
    for _ in range(repeats):
        started = time.perf_counter()
        for _ in range(calls):
            lookup(points)
        timings.append((time.perf_counter() - started) / calls)
    return statistics.median(timings)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--calls", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", default="occupancy_lookup")
    args = parser.parse_args()
    generator = torch.Generator().manual_seed(0)
    rows = []
    for resolution in (32, 64):
        grid = OccupancyGrid(resolution=resolution, aabb=[[-1.5] * 3, [1.5] * 3])
        grid.occupied.copy_(torch.rand(resolution**3, generator=generator) < 0.2)
        if grid.lookup_kernel(torch.zeros(1, 3)) is None:
            sys.exit("the occupancy lookup's kernel is not built here (NERFEXP_KERNELS=off, or no C++ compiler)")

        def torch_path(points: torch.Tensor) -> torch.Tensor:
            index, inside = cell_indices(points, grid.aabb, grid.resolution)
            return inside & grid.occupied[index]

        for name, samples in SAMPLES.items():
            points = torch.rand(RAYS, samples, 3, generator=generator) * 4 - 2
            if not torch.equal(grid.occupied_at(points), torch_path(points)):
                sys.exit(f"the kernel and the torch path disagree at {resolution}^3 cells, {name}")
            fused = seconds_per_call(grid.occupied_at, points, args.calls, args.repeats)
            reference = seconds_per_call(torch_path, points, args.calls, args.repeats)
            rows.append({"cells": resolution, "samples": name, "points": RAYS * samples, "fused_ms": fused * 1e3,
                         "torch_ms": reference * 1e3})
    out = Path(args.out) if Path(args.out).is_absolute() else RESULTS / args.out
    script = Path(__file__).resolve().relative_to(Path(__file__).resolve().parents[1])
    record = {"command": " ".join(["python", str(script), *sys.argv[1:]]), "machine": machine(),
              "torch_threads": torch.get_num_threads(), "rows": rows}
    lines = [f"`{record['command']}` on {record['machine']['device']}: `OccupancyGrid.occupied_at` per call, "
             f"median of {args.repeats} timings of {args.calls} calls, both answers equal.", "",
             "| cells | samples per ray | points | fused kernel (ms) | torch path (ms) | torch / fused |",
             "|---|---|---|---|---|---|"]
    lines += [f"| {r['cells']}^3 | {r['samples']} | {r['points']} | {r['fused_ms']:.3f} | {r['torch_ms']:.3f} | "
              f"{r['torch_ms'] / r['fused_ms']:.1f}x |" for r in rows]
    atomic_write(out.with_suffix(".json"), json.dumps(record, indent=2).encode())
    atomic_write(out.with_suffix(".md"), ("\n".join(lines) + "\n").encode())
    print("\n".join(lines))


if __name__ == "__main__":
    main()
