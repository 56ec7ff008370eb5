"""Quality per unit of training time: the paper's complete model against ``encoding=hashgrid
acceleration=occupancy``, on the built-in scene and on a Blender-format scene that ``nerfexp-scene``
writes (loaded with ``data=blender``, whose box is Blender's [-1.5, 1.5]^3: there the grid must learn
what is empty, as on any user's scene), and with ``--scenes glossy`` on the glossy scene it writes
(``nerfexp-scene --scene glossy``), each variant's best validation PSNR within ``--budget-s`` seconds.
Other variants than the hash grid's: ``--variant "NAME: OVERRIDE ..."`` (repeated), e.g.
``--variant "proposal: hierarchical=proposal"`` for proposal sampling against the hierarchy.

Each variant trains from the same seed with the real config (``scale=cpu`` unless overridden), validating
every ``--val-every`` steps on ``--n-val`` views; the clock counts training only. The target is the
complete model's final validation PSNR after its default run; a variant's time to it is the training
time at its first validation at or above it (the issue that asked for the hash grid's hoped for at most a
third of the complete model's training time).

Writes ``benchmarks/results/time_to_quality.{json,md,png}`` (``--out``). On a GPU (Lightning's
``accelerator=auto`` picks it) ``--gpu`` uses the paper's network sizes and a 400 x 400 scene, and
writes ``time_to_quality_gpu.*``:

    python benchmarks/time_to_quality.py --threads 2          # 2 CPU cores
    python benchmarks/time_to_quality.py --gpu                # a GPU: scale=paper, 20,000 steps
"""

import argparse
import io
import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate
from matplotlib.figure import Figure
from speed import time_to, train

from nerfexp.files import atomic_write

RESULTS = Path(__file__).parent / "results"
FAST = {"hashgrid+occupancy": ["encoding=hashgrid", "acceleration=occupancy"]}  # the variants by default
GPU = {"steps": 20000, "val_every": 1000, "resolution": 400, "overrides": ["scale=paper"]}


def write_blender_scene(folder: Path, resolution: int, scene: str = "builtin") -> Path:
    """A scene of ``nerfexp-scene`` (its console entry; ``builtin`` or ``glossy``) written as a Blender-format
    dataset."""
    subprocess.run([sys.executable, "-m", "nerfexp.commands.scene", str(folder), "--resolution", str(resolution),
                    "--scene", scene], check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return folder


def run_scene(scene_overrides: list[str], overrides: list[str], variants: dict[str, list[str]]) -> dict:
    """The complete model and ``variants`` on one scene: their numbers, curves, and each variant's time to
    the complete model's final validation PSNR."""
    runs, datamodule = {}, None
    for name, variant in {"complete": [], **variants}.items():
        with initialize_config_module("nerfexp.conf", version_base=None):
            cfg = compose("config", overrides=[*scene_overrides, *overrides, *variant])
        datamodule = datamodule or instantiate(cfg.datamodule)  # each scene is loaded once
        _, runs[name] = train(cfg, datamodule)
        print(name, {k: v for k, v in runs[name].items() if k != "curve"}, flush=True)
    complete = runs["complete"]
    target = complete["final_val_psnr"]
    reached = {name: time_to(runs[name]["curve"], target) for name in variants}
    return {"runs": runs, "target_psnr": target, "time_to_target_s": reached,
            "fraction_of_complete_time": {name: None if t is None else t / complete["train_s"]
                                          for name, t in reached.items()}}


def plot(scenes: dict) -> bytes:
    figure = Figure(figsize=(5.5 * len(scenes), 4.2), layout="constrained")
    for axes, (scene, result) in zip(figure.subplots(1, len(scenes), squeeze=False)[0], scenes.items(), strict=True):
        for i, (name, run) in enumerate(result["runs"].items()):
            axes.plot([p["train_s"] for p in run["curve"]], [p["val_psnr"] for p in run["curve"]], marker=".",
                      color=f"C{i}", label=name)
        axes.axhline(result["target_psnr"], color="k", linestyle="--", linewidth=1,
                     label=f"complete's final {result['target_psnr']:.2f} dB")
        axes.set(xlabel="training seconds (validation excluded)", ylabel="validation PSNR (dB)", title=scene)
        axes.grid(alpha=0.3)
        axes.legend(fontsize="small")
    out = io.BytesIO()
    figure.savefig(out, format="png", dpi=100)
    return out.getvalue()


def markdown(report: dict) -> str:
    budget = report["settings"]["budget_s"]
    lines = [f"| scene | variant | steps | train s | s / step | evals / ray (proposals') "
             f"| best val PSNR within {budget:.0f} s | final val PSNR | test PSNR |", "|---" * 9 + "|"]
    for scene, result in report["scenes"].items():
        for name, r in result["runs"].items():
            within = [p["val_psnr"] for p in r["curve"] if p["train_s"] <= budget]
            lines.append(f"| {scene} | {name} | {r['steps']} | {r['train_s']:.0f} | {r['s_per_step']:.3f} | "
                         f"{r['evaluations_per_ray']:.1f} ({r['proposal_samples_per_ray']}) | "
                         f"{max(within, default=float('nan')):.2f} | "
                         f"{r['final_val_psnr']:.2f} | {r['test_psnr']:.2f} |")
    lines.append("")
    for scene, result in report["scenes"].items():
        for name, reached in result["time_to_target_s"].items():
            fraction = result["fraction_of_complete_time"][name]
            when = "never reached" if reached is None else f"reached after {reached:.0f} s, {fraction:.2f} of its time"
            lines.append(f"- {scene}: {name} to complete's final validation PSNR {result['target_psnr']:.2f} dB: "
                         f"{when}.")
    lines += ["", f"Settings: {report['settings']}. Machine: {report['machine']}."]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=None, help="training steps (default: the scale's)")
    parser.add_argument("--val-every", type=int, default=250)
    parser.add_argument("--n-val", type=int, default=4)
    parser.add_argument("--resolution", type=int, default=100, help="the Blender-format scene's image size")
    parser.add_argument("--scenes", default="builtin,blender", help="comma-separated: builtin, blender, glossy")
    parser.add_argument("--budget-s", type=float, default=300.0,
                        help="the table's best validation PSNR within this many training seconds")
    parser.add_argument("--variant", action="append", default=[], metavar="NAME: OVERRIDE ...",
                        help="a variant to set against the complete model (repeatable; default: hashgrid+occupancy)")
    parser.add_argument("--gpu", action="store_true", help="the paper's sizes, 20,000 steps, a 400 x 400 scene")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("overrides", nargs="*", help="config overrides for every run")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if any(":" not in v for v in args.variant):
        parser.error("--variant: expected 'NAME: OVERRIDE ...', e.g. 'proposal: hierarchical=proposal'")
    variants = {name.strip(): rest.split() for name, rest in (v.split(":", 1) for v in args.variant)} or FAST
    steps, val_every, resolution = args.steps, args.val_every, args.resolution
    overrides = list(args.overrides)
    if args.gpu:
        if not torch.cuda.is_available():
            parser.error("--gpu: torch sees no CUDA device here")
        steps, val_every, resolution = steps or GPU["steps"], GPU["val_every"], GPU["resolution"]
        overrides = GPU["overrides"] + overrides
    overrides += [f"scale.val_every={val_every}", f"data.n_val={args.n_val}"]
    overrides += [f"scale.steps={steps}"] if steps else []
    scenes = {}
    with tempfile.TemporaryDirectory() as scratch:
        for scene in args.scenes.split(","):
            if scene == "builtin":
                scene_overrides = ["data=procedural"]  # at the scale's image size (64; 400 with --gpu)
            elif scene in ("blender", "glossy"):  # the built-in scene, the glossy one: Blender-format
                written = "builtin" if scene == "blender" else scene
                root = write_blender_scene(Path(scratch) / scene, resolution, written)
                scene_overrides = ["data=blender", f"data.root={root}"]
            else:
                parser.error(f"--scenes: expected builtin, blender or glossy, got {scene!r}")
            scenes[scene] = run_scene(scene_overrides, overrides, variants)
    machine = {"cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
               "processor": platform.processor() or platform.machine(), "torch": torch.__version__,
               "cuda": torch.cuda.get_device_name() if torch.cuda.is_available() else None}
    report = {"machine": machine, "settings": {"overrides": overrides, "variants": variants,
                                               "blender_resolution": resolution,
                                               "budget_s": args.budget_s, "command": " ".join(sys.argv)},
              "scenes": scenes}
    args.out.mkdir(parents=True, exist_ok=True)
    stem = "time_to_quality_gpu" if args.gpu else "time_to_quality"
    atomic_write(args.out / f"{stem}.json", (json.dumps(report, indent=2) + "\n").encode())
    atomic_write(args.out / f"{stem}.md", markdown(report).encode())
    atomic_write(args.out / f"{stem}.png", plot(scenes))
    print(markdown(report))


if __name__ == "__main__":
    main()
