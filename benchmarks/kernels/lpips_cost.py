"""What scoring one image costs: LPIPS (nerfexp.scoring.perceptual) beside SSIM and PSNR, at the image sizes
nerfexp evaluates (the built-in scene's 100 x 100 to Blender's 800 x 800), on this machine's CPU or GPU.

AlexNet's cost does not depend on its weights, so the network gets random ones in torchvision's layout (no
ImageNet file needed). Each score is timed ``--repeats`` times after one untimed call; the median is kept.
Writes ``benchmarks/results/lpips_cost.json`` and ``.md``.

    python benchmarks/kernels/lpips_cost.py
"""

import argparse
import json
import platform
import statistics
import tempfile
import time
from pathlib import Path

import torch

from nerfexp.files import atomic_write
from nerfexp.scoring.metrics import psnr, ssim
from nerfexp.scoring.perceptual import ALEXNET_FILE, LpipsScorer, alexnet_features, lpips_network

RESULTS = Path(__file__).parents[1] / "results"  # benchmarks/results
SIZES = (100, 200, 400, 800)


def random_alexnet(folder: Path) -> Path:
    """A torchvision-format AlexNet weights file with random weights (``features.*``)."""
    generator = torch.Generator().manual_seed(0)
    state = {f"features.{name}": torch.randn(value.shape, generator=generator) * 0.05
             for name, value in alexnet_features().state_dict().items()}
    path = folder / ALEXNET_FILE
    torch.save(state, path)
    return path


def median_seconds(score, image: torch.Tensor, target: torch.Tensor, repeats: int) -> float:
    score(image, target)  # untimed: first-call allocations
    times = []
    for _ in range(repeats):
        if image.device.type == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        score(image, target)
        if image.device.type == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = parser.parse_args()
    device = torch.device(args.device)
    with tempfile.TemporaryDirectory() as folder:
        scorer = LpipsScorer(lpips_network(random_alexnet(Path(folder))))
    generator = torch.Generator().manual_seed(1)
    rows = []
    for size in SIZES:
        image = torch.rand(size, size, 3, generator=generator).to(device)
        target = (image + 0.05 * torch.randn(image.shape, generator=generator).to(device)).clamp(0, 1)
        row = {"size": size, **{name: median_seconds(score, image, target, args.repeats)
                                for name, score in (("lpips_s", scorer), ("ssim_s", ssim), ("psnr_s", psnr))}}
        rows.append(row)
        print(f"{size} x {size}: LPIPS {row['lpips_s']:.4f} s, SSIM {row['ssim_s']:.4f} s, PSNR {row['psnr_s']:.4f} s")
    name = (torch.cuda.get_device_name(device) if device.type == "cuda"
            else f"CPU ({platform.processor() or platform.machine()}, {torch.get_num_threads()} torch threads)")
    record = {"device": name, "torch": torch.__version__, "repeats": args.repeats, "rows": rows}
    RESULTS.mkdir(exist_ok=True)
    atomic_write(RESULTS / "lpips_cost.json", (json.dumps(record, indent=2) + "\n").encode())
    lines = ["# Scoring one image: LPIPS beside SSIM and PSNR", "",
             f"`python benchmarks/kernels/lpips_cost.py` on {name}, torch {torch.__version__}; median of "
             f"{args.repeats} calls after one untimed, seconds per image (render and target on the device; SSIM and "
             "PSNR on the CPU as nerfexp computes them).", "",
             "| image | LPIPS (s) | SSIM (s) | PSNR (s) |", "|---|---|---|---|"]
    lines += [f"| {r['size']} x {r['size']} | {r['lpips_s']:.4f} | {r['ssim_s']:.4f} | {r['psnr_s']:.4f} |"
              for r in rows]
    atomic_write(RESULTS / "lpips_cost.md", ("\n".join(lines) + "\n").encode())


if __name__ == "__main__":
    main()
