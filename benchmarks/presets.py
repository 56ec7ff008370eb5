"""Named presets against each other on one scene, as a user runs them: ``nerfexp experiment=fast`` against the
complete model (``nerfexp`` with no preset) on the glossy scene (``nerfexp-scene --scene glossy``, 100 x 100, a
Blender-format dataset) or the built-in one (``--scene builtin``), each seed a run of the real console script,
one at a time.

    python benchmarks/presets.py [--seeds 0 1 2] [--preset "NAME: OVERRIDE ..."]... [--once NAME]...
                                 [--target-psnr 28 --budget-s 300] [--resolution 100] [--runs DIR] [--out OUT]

    python benchmarks/presets.py --once complete --target-psnr 28 --runs RUNS    # docs/results/fast_preset

Default presets: ``fast`` (``experiment=fast``) and ``complete`` (the defaults: the paper's model at scale=cpu).
Each run's test PSNR and SSIM, training seconds (validation excluded, as ``results.json`` counts them), seconds
per step and network evaluations per ray; per preset the mean over seeds and, with ``--target-psnr``, how many
runs reached it within ``--budget-s`` training seconds, and the first preset against each other one paired by
seed with a 95% t-interval (``nerfexp.report.comparison``) where they share two seeds or more (``--once NAME``: a
slow preset with the first seed only, compared on it alone). The CPU model and its units are written beside the
figures (``nerfexp.rundir.layout.machine``). Writes ``OUT.json`` and ``OUT.md``; finished runs in ``--runs``
are read again, not retrained.
"""

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

from nerfexp.files import atomic_write
from nerfexp.report.comparison import paired_difference

RESULTS = Path(__file__).parents[1] / "docs" / "results"
PRESETS = {"fast": ["experiment=fast"], "complete": []}
EVERY_RUN = ["logger=none", "model.lpips=false", "trainer.enable_progress_bar=false", "scale.val_every=1000"]


def write_scene(folder: Path, scene: str, resolution: int) -> None:
    """``nerfexp-scene``'s ``scene`` as a Blender-format dataset in ``folder`` (once)."""
    if not (folder / "transforms_train.json").is_file():
        subprocess.run([str(Path(sys.executable).with_name("nerfexp-scene")), str(folder), "--scene", scene,
                        "--resolution", str(resolution)], check=True)


def run(preset: list[str], seed: int, scene: list[str], run_dir: Path) -> dict:
    """One run of ``nerfexp`` with ``preset``'s overrides on the ``scene`` its overrides choose (unless ``run_dir``
    holds a finished one); what its ``results.json`` says."""
    if not (run_dir / "results.json").is_file():
        command = [str(Path(sys.executable).with_name("nerfexp")), *preset, *scene, f"seed={seed}", *EVERY_RUN,
                   f"hydra.run.dir={run_dir}"]
        print(" ".join(command[1:]), flush=True)
        with open(run_dir.with_suffix(".log"), "w") as log:
            subprocess.run(command, check=True, stdout=log, stderr=subprocess.STDOUT)
    result = json.loads((run_dir / "results.json").read_text())
    return {"seed": seed, "psnr": result["test_psnr"], "ssim": result["test_ssim"], "train_s": result["train_time_s"],
            "steps": result["steps"], "s_per_step": result["time_per_step_s"],
            "evaluations_per_ray": result["evaluations_per_ray"],
            "colour_evaluations_per_ray": result.get("colour_evaluations_per_ray"),  # recorded by later nerfexp
            "precision": result["precision"],
            "device": result["machine"]["device"], "choices": result["choices"]}


def markdown(record: dict) -> str:
    target, budget = record["target_psnr"], record["budget_s"]
    size = f" at {record['resolution']} x {record['resolution']}" if record["scene"] == "glossy" else ""
    lines = [f"`{record['command']}`: the {record['scene']} scene{size}, seeds {record['seeds']}, each run alone on "
             f"{record['devices']}.", "",
             "| preset | seed | precision | steps | train s | s / step | evals / ray | test PSNR | test SSIM |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, runs in record["runs"].items():
        lines += [f"| {name} | {r['seed']} | {r['precision']} | {r['steps']} | {r['train_s']:.0f} | "
                  f"{r['s_per_step']:.4f} | {r['evaluations_per_ray']:.1f} | {r['psnr']:.2f} | {r['ssim']:.4f} |"
                  for r in runs]
    goal = "" if target is None else f" runs with >= {target:g} dB within {budget:.0f} s |"
    lines += ["", "| preset | mean test PSNR | mean train s |" + goal, "|---|---|---|" + ("---|" if goal else "")]
    for name, runs in record["runs"].items():
        met = "" if target is None else \
            f" {sum(r['psnr'] >= target and r['train_s'] <= budget for r in runs)} of {len(runs)} |"
        lines.append(f"| {name} | {statistics.mean(r['psnr'] for r in runs):.2f} | "
                     f"{statistics.mean(r['train_s'] for r in runs):.0f} |" + met)
    for key, d in record["differences"].items():
        spread = (f"95% interval [{d['interval'][0]:+.2f}, {d['interval'][1]:+.2f}] ({d['verdict']})"
                  if d["interval"] else "one seed: no interval")
        lines += ["", f"Test PSNR, {key}, paired by seed (n = {d['n']}): {d['mean']:+.2f} dB, {spread}."]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--preset", action="append", default=[], metavar="NAME: OVERRIDE ...",
                        help="a preset (repeatable; default: fast, complete)")
    parser.add_argument("--once", action="append", default=[], metavar="NAME",
                        help="a preset run with the first seed only (repeatable): the slow ones")
    parser.add_argument("--scene", default="glossy", choices=["glossy", "builtin"],
                        help="glossy: written as a Blender-format scene into --runs; builtin: nerfexp's default data")
    parser.add_argument("--resolution", type=int, default=100, help="the glossy scene's image size")
    parser.add_argument("--target-psnr", type=float, default=None,
                        help="count the runs reaching this test PSNR within --budget-s training seconds")
    parser.add_argument("--budget-s", type=float, default=300.0)
    parser.add_argument("--runs", type=Path, default=Path("preset_runs"))
    parser.add_argument("--out", type=Path, default=RESULTS / "fast_preset")
    args = parser.parse_args()
    if any(":" not in p for p in args.preset):
        parser.error("--preset: expected 'NAME: OVERRIDE ...', e.g. 'fast: experiment=fast'")
    presets = {name.strip(): rest.split() for name, rest in (p.split(":", 1) for p in args.preset)} or PRESETS
    args.runs.mkdir(parents=True, exist_ok=True)
    scene = []  # the built-in scene: nerfexp's default data, at the scale's size
    if args.scene == "glossy":
        folder = (args.runs / f"{args.scene}{args.resolution}").resolve()
        write_scene(folder, args.scene, args.resolution)
        scene = ["data=blender", f"data.root={folder}"]
    runs = {name: [run(overrides, seed, scene, args.runs / f"{name}_{seed}")
                   for seed in (args.seeds[:1] if name in args.once else args.seeds)]
            for name, overrides in presets.items()}
    names = list(presets)
    differences = {}
    for other in names[1:]:
        psnrs = {name: {r["seed"]: r["psnr"] for r in runs[name]} for name in (names[0], other)}
        d = paired_difference(psnrs[names[0]], psnrs[other])
        differences[f"{names[0]} - {other}"] = {"mean": d.mean, "n": d.n, "interval": d.interval, "verdict": d.verdict}
    script = Path(__file__).resolve().relative_to(Path(__file__).resolve().parents[1])
    record = {"command": " ".join(["python", str(script), *sys.argv[1:]]), "scene": args.scene,
              "resolution": args.resolution, "seeds": args.seeds, "presets": presets, "target_psnr": args.target_psnr,
              "budget_s": args.budget_s, "runs": runs, "differences": differences,
              "devices": ", ".join(sorted({r["device"] for rs in runs.values() for r in rs}))}
    atomic_write(args.out.with_suffix(".json"), json.dumps(record, indent=2).encode())
    atomic_write(args.out.with_suffix(".md"), markdown(record).encode())
    print(markdown(record))


if __name__ == "__main__":
    main()
