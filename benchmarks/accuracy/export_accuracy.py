"""How near a trained run's export lies to the built-in scene's true surface: ``nerfexp-export``'s mesh at
several density thresholds, and its point cloud, against the scene's exact geometry.

For a run trained on the built-in scene (``data=procedural``, e.g. the default experiment), this extracts
the mesh as ``nerfexp-export`` does (``extract_mesh``: the final field, the run's box, ``--resolution``)
at each of ``--thresholds``, and the points of the test views (``view_points``, opacity >= 0.5), and
measures them with the scene's exact signed distances (``nerfexp.data.procedural.signed_distances``):

- accuracy: each vertex's (point's) distance to the true surface; the share of vertices inside an object;
- completeness: for every pixel of the test views whose ray hits the scene (``intersect_scene``, exact),
  the distance from that visible surface point to the nearest vertex. Only what the test cameras see
  counts: no camera sees the slab's underside.

Distances are in scene units and in grid cells. Writes ``benchmarks/results/export_accuracy.json`` and
``.md``; nothing is written into the run.

    nerfexp hydra.run.dir=outputs/default            # the default experiment (8 minutes on 2 cores)
    python benchmarks/accuracy/export_accuracy.py outputs/default [--resolution 128] [--thresholds 5 20 50]
"""

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from nerfexp.commands.export import trained_run
from nerfexp.data.procedural import ProceduralScene, intersect_scene, signed_distances
from nerfexp.files import atomic_write
from nerfexp.geometry.cameras import camera_rays
from nerfexp.products.mesh import box_text, export_box, extract_mesh, final_field, view_points
from nerfexp.rundir.layout import machine

RESULTS = Path(__file__).parents[1] / "results"  # benchmarks/results
QUANTILES = (0.5, 0.9, 0.99)


def visible_surface(views) -> np.ndarray:
    """The exact surface points [M, 3] that the pixels of ``views`` see (their rays' first hits)."""
    origins, directions = camera_rays(views.c2w.double(), views.height, views.width, views.intrinsics)  # each its lens
    t, _, _ = intersect_scene(origins.reshape(-1, 3), directions.reshape(-1, 3))
    hit = torch.isfinite(t)
    return (origins.reshape(-1, 3)[hit] + t[hit, None] * directions.reshape(-1, 3)[hit]).numpy()


def distance_summary(distances: np.ndarray, cell: float) -> dict:
    return {"n": len(distances), **{f"q{round(q * 100)}": float(np.quantile(distances, q)) for q in QUANTILES},
            "within_1_cell": float((distances <= cell).mean())}


def measure(run: Path, resolution: int, thresholds: list[float]) -> dict:
    (run_dir, checkpoint, _, module, step), scene = trained_run(run, [], None)
    if not isinstance(scene, ProceduralScene):
        raise SystemExit(f"{run_dir}: trained on {type(scene).__name__}, not the built-in scene (data=procedural), "
                         "whose exact geometry this measures against")
    box = export_box(module.renderer, scene)
    cell = ((box[1] - box[0]).max() / resolution).item()
    views = scene.views("test")
    surface = visible_surface(views)
    rows = []
    for threshold in thresholds:
        mesh, _ = extract_mesh(final_field(module.renderer), box, resolution, threshold,
                               module.chunk * module.renderer.samples_per_ray, module.device)
        signed = signed_distances(torch.from_numpy(mesh.vertices)).amin(-1).numpy()
        to_mesh, _ = cKDTree(mesh.vertices).query(surface)
        rows.append({"threshold": threshold, "vertices": len(mesh.vertices), "faces": len(mesh.faces),
                     "inside": float((signed < 0).mean()), "accuracy": distance_summary(np.abs(signed), cell),
                     "completeness": distance_summary(to_mesh, cell)})
    points, _ = view_points(module, scene, views, 0.5)
    point_distances = signed_distances(points.double()).amin(-1).abs().numpy()
    return {"run": str(run_dir), "checkpoint": str(checkpoint), "step": step, "resolution": resolution,
            "box": box.tolist(), "cell": cell, "test_views": len(views), "visible_surface_points": len(surface),
            "meshes": rows, "points": distance_summary(point_distances, cell), "machine": machine()}


def markdown(result: dict) -> str:
    cell = result["cell"]

    def cells(summary: dict) -> str:
        return " | ".join(f"{summary[f'q{round(q * 100)}']:.4f} ({summary[f'q{round(q * 100)}'] / cell:.2f})"
                          for q in QUANTILES) + f" | {100 * summary['within_1_cell']:.1f}%"

    thresholds = " ".join(f"{row['threshold']:g}" for row in result["meshes"])
    lines = ["# How near an export lies to the built-in scene's true surface", "",
             f"    python benchmarks/accuracy/export_accuracy.py {result['run']} --resolution {result['resolution']} "
             f"--thresholds {thresholds}", "",
             f"Checkpoint `{result['checkpoint']}` (step {result['step']}); grid of {result['resolution']} cells along "
             f"the box's longest edge, cells of {cell:.4f}; box {box_text(torch.tensor(result['box']))}. Distances "
             f"in scene units (in cells); quantiles over vertices (accuracy) or over the "
             f"{result['visible_surface_points']} exact surface points that the {result['test_views']} test views' "
             "pixels see (completeness).", "",
             "| threshold | vertices | inside an object | accuracy: median | 90% | 99% | within a cell "
             "| completeness: median | 90% | 99% | within a cell |", "|" + "---|" * 11]
    for row in result["meshes"]:
        lines.append(f"| {row['threshold']:g} | {row['vertices']} | {100 * row['inside']:.0f}% | "
                     f"{cells(row['accuracy'])} | {cells(row['completeness'])} |")
    lines += ["", f"Points (test views, opacity >= 0.5): {result['points']['n']}; distance to the true surface: "
              f"median | 90% | 99% | within a cell: {cells(result['points'])}.", ""]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a run directory of the built-in scene (or a checkpoint in one)")
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--thresholds", type=float, nargs="+", default=[5.0, 20.0, 50.0])
    parser.add_argument("--out", type=Path, default=RESULTS / "export_accuracy")
    args = parser.parse_args()
    result = measure(args.run, args.resolution, args.thresholds)
    atomic_write(args.out.with_suffix(".json"), json.dumps(result, indent=2).encode())
    atomic_write(args.out.with_suffix(".md"), markdown(result).encode())
    print(markdown(result))


if __name__ == "__main__":
    main()
