"""What the appearance embedding buys on ground truth: the built-in scene whose images each have their own exposure
and white balance (``data.appearance_changes``), trained with ``appearance=none`` and ``appearance=embedding``,
paired by seed and scored on the same pixels (the test images' right halves: NeRF-W's protocol for the embedding,
the same pixels of the one render for none).

    python benchmarks/appearance.py [--steps 1000] [--seeds 0 1 2] [--changes train all]

``train``: only the training images vary (photographs taken with automatic exposure; the test images neutral);
``all``: every image, the test images included (NeRF in the Wild's setting). The default experiment at
``scale=cpu`` with 32 x 32 images and 40 training views, one process at a time (run it alone on the machine).
Writes ``docs/results/appearance.md`` and ``.json``: each run's right-half and whole-image test PSNR, the
embedding's gain paired by seed with its 95% interval (``nerfexp.report.comparison``), the CPU and the command.
"""

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

from precision import cpu_model  # benchmarks/precision.py: the CPU's model name

from nerfexp.files import atomic_write
from nerfexp.report.comparison import paired_difference
from nerfexp.rundir.layout import machine

RESULTS = Path(__file__).parents[1] / "docs" / "results"
SIZE = ["scale.image_size=32", "data.n_train=40", "data.n_val=1", "data.n_test=8"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("appearance_runs"))
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--changes", nargs="+", choices=("train", "all"), default=["train", "all"])
    args = parser.parse_args()
    nerfexp = Path(sys.executable).with_name("nerfexp")
    runs = []
    for changes in args.changes:
        for appearance in ("none", "embedding"):
            for seed in args.seeds:
                run_dir = args.out / f"{changes}_{appearance}_{seed}"
                if not (run_dir / "results.json").is_file():
                    command = [str(nerfexp), f"appearance={appearance}", f"data.appearance_changes={changes}", *SIZE,
                               f"scale.steps={args.steps}", f"scale.val_every={args.steps}", f"seed={seed}",
                               "model.lpips=false", "trainer.enable_progress_bar=false", f"hydra.run.dir={run_dir}"]
                    print(" ".join(command[1:]), flush=True)
                    with open(args.out / f"{run_dir.name}.log", "w") as log:
                        subprocess.run(command, check=True, stdout=log, stderr=subprocess.STDOUT)
                result = json.loads((run_dir / "results.json").read_text())
                runs.append({"changes": changes, "appearance": appearance, "seed": seed,
                             "right_half": result["test_psnr_right_half"], "full_image": result["test_psnr_full_image"],
                             "test_protocol": result["test_protocol"], "train_time_s": result["train_time_s"]})
    rows, gains = [], {}
    for changes in args.changes:
        by = {a: {r["seed"]: r for r in runs if r["changes"] == changes and r["appearance"] == a}
              for a in ("none", "embedding")}
        for appearance, seeds in by.items():
            right, whole = (statistics.mean(r[key] for r in seeds.values()) for key in ("right_half", "full_image"))
            rows.append(f"| {changes} | {appearance} | {right:.2f} | {whole:.2f} |")
        for key in ("right_half", "full_image"):
            d = paired_difference({s: r[key] for s, r in by["embedding"].items()},
                                  {s: r[key] for s, r in by["none"].items()})
            gains[f"{changes}/{key}"] = {"mean": d.mean, "n": d.n, "interval": d.interval, "verdict": d.verdict}
    record = {"command": "python " + " ".join(sys.argv), "machine": machine(), "cpu": cpu_model(),
              "steps": args.steps, "seeds": args.seeds, "runs": runs, "embedding_minus_none": gains}
    atomic_write(RESULTS / "appearance.json", json.dumps(record, indent=2).encode())

    def said(g: dict) -> str:
        low, high = g["interval"] if g["interval"] else (float("nan"), float("nan"))
        return f"{g['mean']:+.2f} dB [{low:+.2f}, {high:+.2f}] ({g['verdict']})"

    text = "\n".join([
        "# Per-image appearance on ground truth: what the embedding buys", "",
        f"`{record['command']}` on {record['cpu']} ({record['machine']['device']}): the built-in scene at 32 x 32, "
        f"40 training and 8 test views, each image's exposure (+-1 stop) and white balance (+-0.5 stop per channel) "
        f"its own (`data.appearance_changes`), the default model at `scale=cpu` for {args.steps} steps, seeds "
        f"{args.seeds}; test PSNR means over seeds (each run in `appearance.json`). Right half: NeRF-W's protocol "
        "for the embedding (the code fitted on the left half, the networks frozen), the same pixels of the one "
        "render for none; whole image: the embedding's mean training code.", "",
        "| images varied | appearance | right half (dB) | whole image (dB) |", "|---|---|---|---|", *rows, "",
        "Embedding minus none, paired by seed, 95% t-intervals:", "",
        *[f"- {key.replace('/', ', ')}: {said(g)}" for key, g in gains.items()], "",
    ])
    atomic_write(RESULTS / "appearance.md", text.encode())
    print(text)


if __name__ == "__main__":
    main()
