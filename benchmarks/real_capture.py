"""A real capture in nerfstudio's format, trained at CPU scale: the default model and the hash grid, their test
PSNR / SSIM / LPIPS, and their renders beside the truth.

    python benchmarks/real_capture.py DATA_ROOT NAME [--steps 4000] [--max-side 100]

Each model trains with ``data=nerfstudio data.root=DATA_ROOT scale=cpu`` (every 8th frame a test view where
the file lists no splits), one process at a time (run it alone on the machine), into ``NAME_runs/``.
Writes ``docs/results/NAME.md`` and ``.json`` (scores, the CPU model, the command) and
``docs/results/NAME.png``: per model, its render of the first three test views (with ``--truth``, above the
capture's own images: only where its licence allows them to be shown). LPIPS is
scored only where AlexNet's weights are on the machine (docs/metrics.md); the file says so where they were
not. The capture's own images stay out of this repository: only the renders' picture is written.
"""

import argparse
import json
import subprocess
import sys
from pathlib import Path

from PIL import Image
from precision import cpu_model  # benchmarks/precision.py: the CPU's model name

from nerfexp.files import atomic_write
from nerfexp.rundir.layout import machine

RESULTS = Path(__file__).parents[1] / "docs" / "results"
MODELS = {"default": [], "hashgrid": ["encoding=hashgrid"]}
SHOWN = 3  # test views in the picture


def picture(run_dirs: dict[str, Path], out: Path, truth: bool) -> None:
    """Per model a row of its renders of the first ``SHOWN`` test views, and with ``truth`` a last row of the
    capture's own images."""
    rows = []
    for run_dir in run_dirs.values():
        rows.append([Image.open(path).convert("RGB") for path in sorted((run_dir / "test").glob("r_*.png"))
                     if path.stem.count("_") == 1][:SHOWN])
    if truth:
        first = next(iter(run_dirs.values()))
        rows.append([Image.open(first / "test" / f"r_{k}_target.png").convert("RGB") for k in range(len(rows[0]))])
    width, height = rows[0][0].size
    sheet = Image.new("RGB", (width * len(rows[0]), height * len(rows)), "white")
    for r, row in enumerate(rows):
        for c, image in enumerate(row):
            sheet.paste(image, (c * width, r * height))
    sheet = sheet.resize((sheet.width * 2, sheet.height * 2), Image.NEAREST)
    sheet.save(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("root", type=Path)
    parser.add_argument("name")
    parser.add_argument("--steps", type=int, default=4000)
    parser.add_argument("--max-side", type=int, default=100)
    parser.add_argument("--truth", action="store_true", help="add the capture's own test images to the picture "
                        "(only where its licence allows them to be shown)")
    args = parser.parse_args()
    out = Path(f"{args.name}_runs")
    nerfexp = Path(sys.executable).with_name("nerfexp")
    runs, run_dirs = {}, {}
    for model, overrides in MODELS.items():
        run_dir = run_dirs[model] = out / model
        if not (run_dir / "results.json").is_file():
            command = [str(nerfexp), "data=nerfstudio", f"data.root={args.root.resolve()}", "scale=cpu",
                       f"scale.steps={args.steps}", f"scale.max_side={args.max_side}", *overrides,
                       "trainer.enable_progress_bar=false", f"hydra.run.dir={run_dir.resolve()}"]
            print(" ".join(command[1:]), flush=True)
            out.mkdir(exist_ok=True)
            with open(out / f"{model}.log", "w") as log:
                subprocess.run(command, check=True, stdout=log, stderr=subprocess.STDOUT)
        result = json.loads((run_dir / "results.json").read_text())
        runs[model] = {key: result.get(key) for key in ("test_psnr", "test_ssim", "test_lpips", "train_time_s",
                                                        "steps", "time_per_step_s", "split", "test_views")}
    picture(run_dirs, RESULTS / f"{args.name}.png", args.truth)
    record = {"command": "python " + " ".join(sys.argv), "machine": machine(), "cpu": cpu_model(),
              "root": str(args.root), "runs": runs}
    atomic_write(RESULTS / f"{args.name}.json", json.dumps(record, indent=2).encode())
    rows = []
    for model, run in runs.items():
        lpips = "not scored (no AlexNet weights)" if run["test_lpips"] is None else f"{run['test_lpips']:.3f}"
        rows.append(f"| {model} | {run['test_psnr']:.2f} | {run['test_ssim']:.4f} | {lpips} | "
                    f"{run['train_time_s']:.0f} |")
    where = f"{record['cpu']} ({record['machine']['device']})"
    text = "\n".join([f"# {args.name}", "", f"`{record['command']}` on {where}.", "",
                      "| model | test PSNR (dB) | test SSIM | test LPIPS | training (s) |", "|---|---|---|---|---|",
                      *rows, "", f"Split: {runs['default']['split']}.", "",
                      f"![renders (rows: {', '.join(MODELS)}{', truth' if args.truth else ''})]({args.name}.png)",
                      ""])
    atomic_write(RESULTS / f"{args.name}.md", text.encode())
    print(text)


if __name__ == "__main__":
    main()
