"""nerfexp beside nerfstudio's nerfacto on the same machine, the same scene, split, images and threads: test PSNR
and SSIM against seconds of training for both, each tool's renders of the same test views scored by the same code
(nerfexp's: 8-bit images, SSIM as tf.image.ssim, ``nerfexp.scoring.metrics``).

    python benchmarks/peers/compare.py prepare SOURCE SCENE [--max-side 240]
    python benchmarks/peers/compare.py run SCENE NAME --format nerfstudio --peer-python PEER/bin/python \
        --budgets 60 120 240 420 600 --preset fast=experiment=fast,scale.steps=9000 [--threads 2]

``prepare`` writes a nerfstudio-format capture (SOURCE: a folder holding ``transforms.json``) as both tools will
read it: its images as nerfexp reads them with ``data.max_side`` (whole-factor area averaging), saved as 8-bit PNGs,
the lens scaled with them, the poses as the file gives them (each tool normalizes them its own way), and the split
nerfexp makes (every 8th frame a test view) written as the file's train/val/test lists, which both tools honour.
A Blender-format scene (``nerfexp-scene``'s) needs no preparing: both read its three files.

``run`` trains, one process at a time (run it alone on the machine):
- each nerfexp preset (``--preset NAME=OVERRIDE,OVERRIDE``), scored at 1/8, 1/4, 1/2, 3/4 of its steps and at
  its end (``test_budgets``: the test views rendered and scored outside its training clock);
- nerfacto with nerfstudio's own settings for the format (``NS_ARGS``: its defaults for a capture; for the Blender
  format the settings nerfstudio's documentation gives for its synthetic scenes), in the peer's environment
  (``--peer-python``), its test views rendered at each of ``--budgets`` seconds of its training clock
  (benchmarks/peers/nerfacto_run.py), then scored here.

Writes ``docs/results/peers_NAME.md`` and ``.json`` (every point, the commands, the CPU, both tools' torch, the
threads and the machine's load) and ``docs/results/peers_NAME.png`` (PSNR against training seconds).
"""

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from PIL import Image  # noqa: E402

from nerfexp.data.blender import BlenderScene  # noqa: E402
from nerfexp.data.nerfstudio import NerfstudioScene  # noqa: E402
from nerfexp.data.views import Views  # noqa: E402
from nerfexp.files import atomic_write  # noqa: E402
from nerfexp.pixels import to_uint8  # noqa: E402
from nerfexp.rundir.layout import cpu_model  # noqa: E402
from nerfexp.scoring.metrics import psnr, ssim  # noqa: E402

RESULTS = Path(__file__).parents[2] / "docs" / "results"
HERE = Path(__file__).parent
BUDGET_FRACTIONS = [0.125, 0.25, 0.5, 0.75]  # nerfexp's test budgets, fractions of its steps; the end is the last
NO_EVAL = ["--vis", "tensorboard", "--viewer.quit-on-train-completion", "True", "--steps-per-eval-batch", "1000000",
           "--steps-per-eval-image", "1000000", "--steps-per-eval-all-images", "1000000",
           "--max-num-iterations", "1000000"]  # the driver stops at its last budget
NS_ARGS = {  # nerfacto's settings per format, after the device and NO_EVAL; then the data parser and its folder
    "nerfstudio": [],  # its defaults for a capture
    # nerfstudio's documented settings for its synthetic (Blender) scenes: white background, near 2, far 6, no
    # contraction, no camera refinement, no appearance embedding at test time, no distortion loss
    "blender": ["--pipeline.model.background-color", "white", "--pipeline.model.proposal-initial-sampler", "uniform",
                "--pipeline.model.near-plane", "2.", "--pipeline.model.far-plane", "6.",
                "--pipeline.model.camera-optimizer.mode", "off",
                "--pipeline.model.use-average-appearance-embedding", "False",
                "--pipeline.model.distortion-loss-mult", "0", "--pipeline.model.disable-scene-contraction", "True"],
}
PARSERS = {"nerfstudio": "nerfstudio-data", "blender": "blender-data"}


def scene_of(root: Path, fmt: str, max_side: int | None = None):
    """nerfexp's reader of the scene in ``root`` (``fmt``: nerfstudio or blender)."""
    if fmt == "nerfstudio":
        return NerfstudioScene(root=str(root), max_side=max_side)
    return BlenderScene(root=str(root))


def prepare(source: Path, out: Path, max_side: int) -> None:
    """``source``'s capture written to ``out`` as both tools read it (the module's docstring)."""
    scene = scene_of(source, "nerfstudio", max_side)
    meta = json.loads((source / "transforms.json").read_text())
    frames = scene.capture().frames
    (out / "images").mkdir(parents=True, exist_ok=True)
    lists, written, lens = {}, [], None
    for split in ("train", "test"):
        views: Views = scene.views(split)
        names = []
        for k, i in enumerate(scene.split_index(split).tolist()):
            name = f"images/{Path(frames[i].file_path).stem}.png"
            Image.fromarray(to_uint8(views.rgba[k, ..., :3])).save(out / name)
            original = next(f for f in meta["frames"] if f["file_path"] == frames[i].file_path)
            written.append({"file_path": name, "transform_matrix": original["transform_matrix"]})
            names.append(name)
        params = views.intrinsics.params
        if not torch.equal(params, params[:1].expand_as(params)) or (lens is not None and not torch.equal(params[0], lens)):
            sys.exit("prepare: the capture's frames have lenses of their own; this script writes one lens")
        lens, size = params[0], (views.height, views.width)
        lists[f"{split}_filenames"] = names
    lists["val_filenames"] = lists["test_filenames"][:2]
    fx, fy, cx, cy = lens.tolist()
    kept = {key: meta[key] for key in ("camera_model", "k1", "k2", "k3", "k4", "p1", "p2", "aabb_scale") if key in meta}
    header = {**kept, "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": size[1], "h": size[0]}
    written.sort(key=lambda frame: frame["file_path"])
    atomic_write(out / "transforms.json", json.dumps({**header, "frames": written, **lists}, indent=1).encode())
    print(f"prepared {len(written)} frames at {size[1]} x {size[0]} in {out}")


def test_targets(scene_root: Path, fmt: str) -> dict[str, torch.Tensor]:
    """The test views' images as nerfexp scores them (RGB on the scene's white background), by file stem."""
    views = scene_of(scene_root, fmt).views("test")
    targets = views.rgb_on(torch.ones(3))
    return {Path(views.sources[k].path).stem: targets[k] for k in range(len(views))}


def scores(renders: dict[str, torch.Tensor], targets: dict[str, torch.Tensor]) -> tuple[float, float]:
    """Mean PSNR and SSIM of ``renders`` against ``targets`` (the same names, every one)."""
    if set(renders) != set(targets):
        sys.exit(f"the renders {sorted(renders)[:3]}... are not the test views {sorted(targets)[:3]}...")
    values = [(psnr(renders[n], targets[n]), ssim(renders[n], targets[n])) for n in sorted(targets)]
    return float(np.mean([v[0] for v in values])), float(np.mean([v[1] for v in values]))


def read_png(path: Path) -> torch.Tensor:
    return torch.from_numpy(np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255)


def load_seconds(start: tuple[float, float]) -> float:
    """The CPUs the machine kept busy on average since ``start`` (``machine_busy``'s), this process's children
    included: a timing is only this tool's where it is about the threads it ran."""
    now = machine_busy()
    return (now[0] - start[0]) / max(now[1] - start[1], 1e-9)


def machine_busy() -> tuple[float, float]:
    """(busy CPU seconds of the whole machine, wall seconds) now, from /proc/stat."""
    fields = Path("/proc/stat").read_text().splitlines()[0].split()[1:]
    ticks = [int(x) for x in fields]
    idle = ticks[3] + ticks[4]
    return (sum(ticks) - idle) / os.sysconf("SC_CLK_TCK"), time.monotonic()


def run_nerfexp(scene: Path, fmt: str, name: str, overrides: list[str], out: Path, threads: int) -> dict:
    """One nerfexp preset trained on ``scene``: its budgets' (seconds, PSNR, SSIM) from results.json, and its final
    renders rescored here (the same code: equal to its own final scores)."""
    run_dir = out / f"nerfexp_{name}"
    # the images as prepared (scale=cpu shrinks them to 100 pixels a side) and every test view of a Blender scene
    # (scale=cpu scores every 8th): as nerfacto reads and renders them
    as_nerfacto = ["data.max_side=null", *(["data.test_stride=1"] if fmt == "blender" else [])]
    command = ["nerfexp", f"data={fmt}", f"data.root={scene}", *as_nerfacto, *overrides, f"threads={threads}", "logger=none",
               f"test_budgets=[{','.join(map(str, BUDGET_FRACTIONS))}]", "model.lpips=false",
               "trainer.enable_progress_bar=false", f"hydra.run.dir={run_dir}"]
    busy = machine_busy()
    subprocess.run(command, check=True)
    results = json.loads((run_dir / "results.json").read_text())
    targets = test_targets(scene, fmt)
    stems = list(targets)
    renders = {stems[k]: read_png(run_dir / "test" / f"r_{k}.png") for k in range(len(stems))}
    final = scores(renders, targets)
    points = [{"train_s": b["train_time_s"], "step": b["step"], "psnr": b["test_psnr"], "ssim": b["test_ssim"]}
              for b in results["test_budgets"]]
    return {"tool": f"nerfexp {name}", "command": command, "points": points, "final_rescored": final,
            "torch": torch.__version__, "threads": results.get("torch_threads"), "machine_busy_cpus":
            load_seconds(busy), "other_load": results.get("other_load")}


def run_nerfacto(scene: Path, fmt: str, budgets: list[float], peer_python: str, out: Path, threads: int) -> dict:
    """nerfacto trained on ``scene`` in its own environment, its renders at each budget scored here."""
    folder = out / "nerfacto"
    command = [peer_python, str(HERE / "nerfacto_run.py"), str(folder), "--budgets", *map(str, budgets), "--threads",
               str(threads), "--", "--machine.device-type", "cpu", *NO_EVAL, *NS_ARGS[fmt], PARSERS[fmt], "--data",
               str(scene)]
    busy = machine_busy()
    subprocess.run(command, check=True)
    record = json.loads((folder / "nerfacto.json").read_text())
    targets = test_targets(scene, fmt)
    points = []
    for budget in record["budgets"]:
        renders = {path.stem: read_png(path) for path in (folder / budget["folder"]).glob("*.png")}
        value = scores(renders, targets)
        points.append({"train_s": budget["train_s"], "step": budget["step"], "psnr": value[0], "ssim": value[1]})
    return {"tool": "nerfstudio nerfacto", "command": command, "points": points, "torch": record["torch"],
            "threads": record["threads"], "machine_busy_cpus": load_seconds(busy)}


def plot(entries: list[dict], path: Path, title: str) -> None:
    figure, axis = plt.subplots(figsize=(6, 4), dpi=110)
    for entry in entries:
        xs = [p["train_s"] for p in entry["points"]]
        axis.plot(xs, [p["psnr"] for p in entry["points"]], marker="o", label=entry["tool"])
    axis.set_xlabel("training time (s)")
    axis.set_ylabel("test PSNR (dB)")
    axis.set_title(title)
    axis.grid(alpha=0.3)
    axis.legend()
    figure.tight_layout()
    figure.savefig(path)


def table(entries: list[dict]) -> list[str]:
    lines = ["| tool | step | training (s) | test PSNR (dB) | test SSIM |", "|---|---|---|---|---|"]
    for entry in entries:
        for p in entry["points"]:
            lines.append(f"| {entry['tool']} | {p['step']:,} | {p['train_s']:.0f} | {p['psnr']:.2f} | "
                         f"{p['ssim']:.3f} |")
    return lines


def run(args: argparse.Namespace) -> None:
    out = Path(args.out or f"peers_{args.name}_runs")
    out.mkdir(parents=True, exist_ok=True)
    entries = []
    for preset in args.preset:
        name, _, overrides = preset.partition("=")
        entries.append(run_nerfexp(args.scene, args.format, name, [o for o in overrides.split(",") if o], out,
                                   args.threads))
    entries.append(run_nerfacto(args.scene, args.format, args.budgets, args.peer_python, out, args.threads))
    record = {"name": args.name, "scene": str(args.scene), "format": args.format, "cpu": cpu_model(
        Path("/proc/cpuinfo").read_text()), "command": sys.argv, "entries": entries}
    atomic_write(RESULTS / f"peers_{args.name}.json", json.dumps(record, indent=1).encode())
    plot(entries, RESULTS / f"peers_{args.name}.png", f"{args.name}: test PSNR against training time")
    lines = [f"# nerfexp beside nerfacto: {args.name}", "", f"CPU: {record['cpu']}; threads: {args.threads}. "
             f"Command: `python {' '.join(sys.argv)}`.", "", *table(entries), "",
             f"![PSNR against training time](peers_{args.name}.png)", ""]
    atomic_write(RESULTS / f"peers_{args.name}.md", "\n".join(lines).encode())
    print("\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    p = commands.add_parser("prepare")
    p.add_argument("source", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--max-side", type=int, default=240)
    r = commands.add_parser("run")
    r.add_argument("scene", type=Path)
    r.add_argument("name")
    r.add_argument("--format", choices=sorted(NS_ARGS), required=True)
    r.add_argument("--peer-python", required=True)
    r.add_argument("--budgets", type=float, nargs="+", required=True, help="nerfacto's, in seconds of training")
    r.add_argument("--preset", action="append", default=[], help="NAME=OVERRIDE,OVERRIDE,... (repeatable)")
    r.add_argument("--threads", type=int, default=2)
    r.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    if args.command == "prepare":
        prepare(args.source, args.out, args.max_side)
    else:
        run(args)


if __name__ == "__main__":
    main()
