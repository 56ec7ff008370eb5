"""What view dependence buys on the glossy scene, object by object, and where the networks put the mirror.

For each run directory given (runs on a scene written by ``nerfexp-scene OUT --scene glossy`` and
loaded with ``data=blender data.root=OUT``; for instance the sweep
``nerfexp -m view_dependence=none,mlp,sh data=blender data.root=OUT``), the run's test views are
rendered with the weights its test scored. Each pixel belongs to the object its centre ray hits
(``nerfexp.data.glossy.intersect_glossy``, exact): the base, the mirror sphere, the torus, or the
background. Per object: the PSNR over its pixels of all test views.

And the mirror's depth. A field without view dependence can still reproduce a mirror seen from many
views, by putting what it reflects *inside* it: a convex mirror of radius r images distant things as a
virtual image up to r / 2 behind its surface, and a diffuse field can paint that image there. The median
of (rendered depth - true depth) over the mirror's pixels says how far behind the surface the networks
put what they show: about 0 for a surface, towards r / 2 for a virtual image. The base and the torus,
whose reflections are faint, are the control: their depth error should be about 0.

Writes ``benchmarks/results/view_dependence.{json,md}`` (``--out``):

    python benchmarks/accuracy/view_dependence.py RUN_DIR [RUN_DIR ...]
"""

import argparse
import json
import math
from pathlib import Path

import torch
from hydra.utils import instantiate

from nerfexp.data.glossy import MIRROR, intersect_glossy
from nerfexp.files import atomic_write
from nerfexp.products.trained import load_module
from nerfexp.rundir.layout import RESULTS, read_json
from nerfexp.rundir.trained import find_run, run_config

OUT = Path(__file__).parents[1] / "results"  # benchmarks/results
OBJECTS = ("base", "mirror", "torus", "background")  # intersect_glossy's indices, then the misses
QUARTILES = torch.tensor([0.25, 0.5, 0.75], dtype=torch.float64)


@torch.no_grad()
def analyse(path: Path) -> dict:
    """Per-object PSNR and the mirror's depth error of one run's test views."""
    run_dir, checkpoint = find_run(path)
    cfg = run_config(run_dir)
    model, steps = load_module(cfg, checkpoint)
    model.eval()
    datamodule = instantiate(cfg.datamodule)
    squared = {name: 0.0 for name in OBJECTS}
    counts = {name: 0 for name in OBJECTS}
    depth_errors = {name: [] for name in OBJECTS[:-1]}
    for batch in datamodule.test_dataloader():
        image = model.render_image(batch["origins"], batch["directions"], batch.get("viewdirs"))
        origins, directions = batch["origins"].double(), batch["directions"].double()  # [H, W, 3]
        length = torch.linalg.vector_norm(directions, dim=-1)  # distance per unit of t
        distance, _, index = intersect_glossy(origins, directions / length[..., None])
        labels = torch.where(torch.isfinite(distance), index, len(OBJECTS) - 1)  # [H, W]
        error = ((image["rgb"].double() - batch["rgb"].double()) ** 2).mean(-1)  # [H, W]
        depth = image["depth"].double() * length  # [H, W], a distance like ``distance``
        for k, name in enumerate(OBJECTS):
            on = labels == k
            squared[name] += float(error[on].sum())
            counts[name] += int(on.sum())
            if name in depth_errors:
                depth_errors[name].append(depth[on] - distance[on])
    results = read_json(run_dir / RESULTS) or {}
    return {
        "run": str(run_dir), "steps": steps,
        "overrides": [o for o in results.get("overrides", []) if not o.startswith(("data.root=", "hydra."))],
        "test_psnr": results.get("test_psnr"),
        "psnr_by_object": {name: -10 * math.log10(squared[name] / counts[name]) if counts[name] else None
                           for name in OBJECTS},
        "pixels_by_object": counts,
        "depth_error_quartiles": {name: [float(q) for q in torch.quantile(torch.cat(errors), QUARTILES)]
                                  for name, errors in depth_errors.items()},
    }


def markdown(runs: list[dict]) -> str:
    radius = MIRROR[1]
    lines = ["| run | steps | test PSNR | " + " | ".join(f"{n} PSNR" for n in OBJECTS)
             + " | " + " | ".join(f"{n}: depth error" for n in OBJECTS[:-1]) + " |",
             "|---|---|---|" + "---|" * (2 * len(OBJECTS) - 1)]
    for r in runs:
        by_object = " | ".join("–" if r["psnr_by_object"][n] is None else f"{r['psnr_by_object'][n]:.2f}"
                               for n in OBJECTS)
        depths = " | ".join(f"{m:+.3f} [{lo:+.3f}, {hi:+.3f}]" for lo, m, hi in r["depth_error_quartiles"].values())
        label = " ".join(r["overrides"]) or "default"
        lines.append(f"| {label} | {r['steps']} | {r['test_psnr']:.2f} | {by_object} | {depths} |")
    lines += ["", "PSNR in dB over each object's pixels of all test views; depth error: rendered minus true "
              "distance along the pixel's centre ray, median [quartiles], in scene units.",
              "", f"Pixels per object (all test views): {runs[0]['pixels_by_object']}. The mirror's radius is "
              f"{radius}: a virtual image of distant things lies up to {radius / 2} behind its surface.",
              "", "Command: `python benchmarks/accuracy/view_dependence.py " + " ".join(r["run"] for r in runs) + "`."]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run directories of runs on the glossy scene")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    runs = [analyse(path) for path in args.runs]
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write(args.out / "view_dependence.json", (json.dumps(runs, indent=2) + "\n").encode())
    atomic_write(args.out / "view_dependence.md", markdown(runs).encode())
    print(markdown(runs))


if __name__ == "__main__":
    main()
