"""The occupancy grid's remedies for the hash grid's low, patchy densities in free space
(benchmarks/results/grid_skipping.md), against the hash grid with the grid as it is and against the positional
encoding with the grid (the reference: what the hash grid should skip as well as), paired by seed on two scenes.

    python benchmarks/grid_remedies.py [--steps 1000] [--seeds 0 1 2] [--scene builtin glossy]
                                       [--variant NAME]... [--runs DIR] [--out OUT]

Every run: ``acceleration=occupancy``, float32 (``trainer.precision=32-true``), ``scale.steps=STEPS``, a run of
the real console script, one at a time (``presets.run``: finished runs in ``--runs`` are read again, not
retrained). Variants (``VARIANTS``): ``posenc_grid``, ``hashgrid_grid``, and the hash grid with each remedy of
docs/acceleration.md, alone and combined: ``alpha`` (``acceleration.grid.alpha_threshold``), ``sparsity_*``
(``model.renderer.sparsity_weight``), ``march_steps`` (``acceleration.grid.march_steps``), ``update_occupied``
(``acceleration.grid.update_occupied``). Per run: test PSNR, density and colour evaluations per ray, seconds per
step; per scene and variant the paired differences by seed (95% t-interval, ``nerfexp.report.comparison``)
against ``hashgrid_grid`` and against ``posenc_grid``. The CPU model is written beside the figures. Writes
``OUT.json`` and ``OUT.md`` (default ``benchmarks/results/grid_remedies``).
"""

import argparse
import json
import statistics
import sys
from pathlib import Path

from presets import run, write_scene  # benchmarks/presets.py: a run of the console script, the glossy scene

from nerfexp.files import atomic_write
from nerfexp.report.comparison import paired_difference
from nerfexp.rundir.layout import machine

RESULTS = Path(__file__).parent / "results"
GRID = ["acceleration=occupancy", "trainer.precision=32-true"]
HASHGRID = ["encoding=hashgrid", *GRID]
ALPHA = "acceleration.grid.alpha_threshold=0.01"  # nerfacc's value for its unbounded scenes
MARCH = "acceleration.grid.march_steps=256"  # Instant-NGP's ratio: 1024 steps over a 128-cell grid, at 32 cells
OCCUPIED = "acceleration.grid.update_occupied=true"
VARIANTS = {
    "posenc_grid": ["encoding=posenc", *GRID],
    "hashgrid_grid": HASHGRID,
    "alpha": [*HASHGRID, ALPHA],
    "sparsity_1e-5": [*HASHGRID, "model.renderer.sparsity_weight=1e-5"],
    "sparsity_1e-4": [*HASHGRID, "model.renderer.sparsity_weight=1e-4"],
    "march_steps": [*HASHGRID, MARCH],
    "march_steps_96": [*HASHGRID, "acceleration.grid.march_steps=96"],
    "march_steps_128": [*HASHGRID, "acceleration.grid.march_steps=128"],
    "march_steps_64": [*HASHGRID, "acceleration.grid.march_steps=64"],
    "march_steps_64_alpha": [*HASHGRID, "acceleration.grid.march_steps=64", ALPHA],
    "update_occupied": [*HASHGRID, OCCUPIED],
    "grid_rules": [*HASHGRID, MARCH, OCCUPIED],
    "grid_rules_alpha": [*HASHGRID, MARCH, OCCUPIED, ALPHA],
    "all": [*HASHGRID, MARCH, OCCUPIED, ALPHA, "model.renderer.sparsity_weight=1e-5"],
}
BASELINES = ("hashgrid_grid", "posenc_grid")  # each variant is compared with both
MEASURES = {"psnr": "test PSNR (dB)", "evaluations_per_ray": "density evaluations / ray",
            "colour_evaluations_per_ray": "colour evaluations / ray", "s_per_step": "s / step"}


def differences(runs: dict[str, list[dict]]) -> dict[str, dict]:
    """{"VARIANT - BASELINE": {measure: {mean, n, interval, verdict}}} for each variant against each baseline
    it is not, paired by seed."""
    found = {}
    for baseline in (b for b in BASELINES if b in runs):
        for name in (n for n in runs if n != baseline):
            found[f"{name} - {baseline}"] = {}
            for measure in MEASURES:
                values = {n: {r["seed"]: r[measure] for r in runs[n] if r[measure] is not None}
                          for n in (name, baseline)}
                d = paired_difference(values[name], values[baseline])
                found[f"{name} - {baseline}"][measure] = {"mean": d.mean, "n": d.n, "interval": d.interval,
                                                          "verdict": d.verdict}
    return found


def cell(d: dict, digits: int) -> str:
    if d["interval"] is None:
        return f"{d['mean']:+.{digits}f}"
    low, high = d["interval"]
    return f"{d['mean']:+.{digits}f} [{low:+.{digits}f}, {high:+.{digits}f}]"


def markdown(record: dict) -> str:
    lines = [f"`{record['command']}` on {record['machine']['device']} (host {record['machine']['host']}): "
             f"{record['steps']} steps, seeds {record['seeds']}, float32, each run of `nerfexp` alone; the runs "
             f"report {record['devices']}.", ""]
    for scene, runs in record["scenes"].items():
        lines += [f"## {scene}", "", "| variant | test PSNR | density evals / ray | colour evals / ray | s / step |",
                  "|---|---|---|---|---|"]
        for name, rs in runs.items():
            means = [statistics.mean(r[m] for r in rs) if all(r[m] is not None for r in rs) else float("nan")
                     for m in MEASURES]
            lines.append(f"| {name} | {means[0]:.2f} | {means[1]:.1f} | {means[2]:.1f} | {means[3]:.4f} |")
        lines += ["", "Paired by seed (mean difference, 95% interval where two seeds or more):", "",
                  "| comparison | " + " | ".join(MEASURES.values()) + " |", "|---" * (len(MEASURES) + 1) + "|"]
        for key, ds in record["differences"][scene].items():
            lines.append(f"| {key} | " + " | ".join(cell(ds[m], 4 if m == "s_per_step" else 2) for m in MEASURES)
                         + " |")
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--scene", nargs="+", default=["builtin", "glossy"], choices=["builtin", "glossy"])
    parser.add_argument("--resolution", type=int, default=100, help="the glossy scene's image size")
    parser.add_argument("--variant", action="append", choices=list(VARIANTS), default=[],
                        help="run only these variants (repeatable; the baselines always run)")
    parser.add_argument("--runs", type=Path, default=Path("grid_remedies_runs"))
    parser.add_argument("--out", type=Path, default=RESULTS / "grid_remedies")
    args = parser.parse_args()
    chosen = {name: VARIANTS[name] for name in VARIANTS if name in BASELINES or not args.variant
              or name in args.variant}
    args.runs.mkdir(parents=True, exist_ok=True)
    scenes, found = {}, {}
    for scene_name in args.scene:
        scene = []  # the built-in scene: nerfexp's default data, at the scale's size
        if scene_name == "glossy":
            folder = (args.runs / f"glossy{args.resolution}").resolve()
            write_scene(folder, "glossy", args.resolution)
            scene = ["data=blender", f"data.root={folder}"]
        scenes[scene_name] = {
            name: [run([*overrides, f"scale.steps={args.steps}"], seed, scene,
                       args.runs / f"{scene_name}_{name}_{args.steps}_{seed}") for seed in args.seeds]
            for name, overrides in chosen.items()}
        found[scene_name] = differences(scenes[scene_name])
    script = Path(__file__).resolve().relative_to(Path(__file__).resolve().parents[1])
    record = {"command": " ".join(["python", str(script), *sys.argv[1:]]), "steps": args.steps, "seeds": args.seeds,
              "variants": chosen, "machine": machine(), "scenes": scenes, "differences": found,
              "devices": ", ".join(sorted({r["device"] for runs in scenes.values() for rs in runs.values()
                                           for r in rs}))}
    atomic_write(args.out.with_suffix(".json"), json.dumps(record, indent=2).encode())
    atomic_write(args.out.with_suffix(".md"), markdown(record).encode())
    print(markdown(record))


if __name__ == "__main__":
    main()
