"""What a real camera's intrinsics are worth, on ground truth: the built-in scene seen through a real lens
(``nerfexp-scene --format nerfstudio --lens real``: principal point off the centre, fx != fy, OPENCV
distortion) trained three ways, against the same scene seen through the ideal pinhole.

    python benchmarks/real_cameras.py [--resolution 64] [--steps 1500] [--seeds 0 1] [--encodings default hashgrid]

- ``pinhole``: the scene rendered through the Blender camera, read as such (the reference);
- ``real``: the scene rendered through the real lens, read with its lens (``data=nerfstudio``);
- ``ignored``: the same images read as a centred pinhole of focal length fx without distortion (what a
  reader that ignores the intrinsics, nerfexp's before ``data=nerfstudio``, trained).

Each with the default model and the hash grid (``encoding=hashgrid``) at ``scale=cpu``, the given steps
and seeds, one process at a time (run it alone on the machine). Writes ``docs/results/real_cameras.md`` and
``.json``: test PSNR and SSIM per run and their means, the CPU model and the command.
"""

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

from precision import cpu_model  # benchmarks/precision.py: the CPU's model name
from sheets import side_by_side  # benchmarks/sheets.py

from nerfexp.files import atomic_write
from nerfexp.rundir.layout import machine

RESULTS = Path(__file__).parents[1] / "docs" / "results"
ENCODINGS = {"default": [], "hashgrid": ["encoding=hashgrid"]}  # --encodings chooses among them


def write_scenes(out: Path, resolution: int, bin_dir: Path) -> dict[str, tuple[Path, str]]:
    """The three readings of the two scenes: name -> (scene folder, transforms file name)."""
    for lens in ("real", "pinhole"):
        if not (out / lens / "transforms.json").is_file():
            subprocess.run([str(bin_dir / "nerfexp-scene"), str(out / lens), "--format", "nerfstudio", "--lens", lens,
                            "--resolution", str(resolution), "--n-train", "100", "--n-val", "2", "--n-test", "20"],
                           check=True, stdout=subprocess.DEVNULL)
    content = json.loads((out / "real" / "transforms.json").read_text())
    ignored = {**content, "camera_model": "PINHOLE", "fl_y": content["fl_x"], "cx": resolution / 2,
               "cy": resolution / 2}
    for key in ("k1", "k2", "k3", "p1", "p2"):
        ignored.pop(key, None)
    (out / "real" / "transforms_ignored.json").write_text(json.dumps(ignored))
    return {"pinhole": (out / "pinhole", "transforms.json"), "real": (out / "real", "transforms.json"),
            "ignored": (out / "real", "transforms_ignored.json")}


def picture(out: Path, encoding: str, seed: int, view: int = 3) -> None:
    """Test view ``view`` as the three readings render it (pinhole, real, ignored) and the real scene's truth,
    side by side, 3 times enlarged: ``docs/results/real_cameras.png``."""
    runs = {reading: out / f"{encoding}_{reading}_{seed}" / "test" for reading in ("pinhole", "real", "ignored")}
    paths = [run / f"r_{view}.png" for run in runs.values()] + [runs["real"] / f"r_{view}_target.png"]
    side_by_side(paths, RESULTS / "real_cameras.png")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("real_cameras_runs"))
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--encodings", nargs="+", choices=sorted(ENCODINGS), default=sorted(ENCODINGS))
    args = parser.parse_args()
    bin_dir = Path(sys.executable).parent
    scenes = write_scenes(args.out, args.resolution, bin_dir)
    runs = []
    for encoding in args.encodings:
        overrides = ENCODINGS[encoding]
        for reading, (root, transforms) in scenes.items():
            for seed in args.seeds:
                run_dir = args.out / f"{encoding}_{reading}_{seed}"
                if not (run_dir / "results.json").is_file():
                    command = [str(bin_dir / "nerfexp"), "data=nerfstudio", f"data.root={root}",
                               f"data.transforms={transforms}", "data.near=2", "data.far=6", "scale=cpu",
                               f"scale.steps={args.steps}", f"scale.val_every={args.steps}", f"seed={seed}",
                               *overrides, "trainer.enable_progress_bar=false", f"hydra.run.dir={run_dir}"]
                    print(" ".join(command[1:]), flush=True)
                    with open(args.out / f"{run_dir.name}.log", "w") as log:
                        subprocess.run(command, check=True, stdout=log, stderr=subprocess.STDOUT)
                result = json.loads((run_dir / "results.json").read_text())
                runs.append({"encoding": encoding, "reading": reading, "seed": seed,
                             "test_psnr": result["test_psnr"], "test_ssim": result["test_ssim"],
                             "train_time_s": result["train_time_s"]})
    means = {f"{e}/{r}": {key: statistics.mean(run[key] for run in runs if run["encoding"] == e and run["reading"] == r)
                          for key in ("test_psnr", "test_ssim")} for e in args.encodings for r in scenes}
    record = {"command": "python " + " ".join(sys.argv), "machine": machine(), "cpu": cpu_model(),
              "resolution": args.resolution, "steps": args.steps, "seeds": args.seeds, "runs": runs, "means": means}
    atomic_write(RESULTS / "real_cameras.json", json.dumps(record, indent=2).encode())
    picture(args.out, args.encodings[0], args.seeds[0])
    rows = [f"| {key.replace('/', ' | ')} | {value['test_psnr']:.2f} | {value['test_ssim']:.4f} |"
            for key, value in means.items()]
    text = "\n".join([
        "# Real cameras on ground truth", "",
        f"`{record['command']}` on {record['cpu']} ({record['machine']['device']}): the built-in scene at "
        f"{args.resolution} x {args.resolution}, "
        f"100 training and 20 test views, `scale=cpu` for {args.steps} steps, seeds {args.seeds}, means over seeds "
        "(each run in `real_cameras.json`).", "",
        "| model | reading | test PSNR (dB) | test SSIM |", "|---|---|---|---|", *rows, "",
        f"![test view 3: pinhole, real, ignored ({args.encodings[0]}, seed {args.seeds[0]}), and the real lens's "
        "truth](real_cameras.png)", "",
    ])
    atomic_write(RESULTS / "real_cameras.md", text.encode())
    print(text)


if __name__ == "__main__":
    main()
