"""The compositing kernel against the torch path it replaces: one forward and backward of
``nerfexp.nerf.compositing.rendered`` (the weights, colour, opacity and depth of sampled rays, and the gradients of
the densities and colours) at the shapes of a ``scale=cpu`` step, the median of ``--repeats`` after a warm-up,
with the kernel and with ``NERFEXP_KERNELS=off``. Both are checked against each other first.

    python benchmarks/compositing.py [--rays 256] [--samples 24 72 96] [--repeats 200] [--threads N] [--out NAME]

Shapes: 24 and 72 samples per ray are the coarse and fine networks' of ``scale=cpu`` (``n_coarse``, ``n_coarse +
n_fine``), 96 the one network's without hierarchy. Writes ``benchmarks/results/NAME.{json,md}`` (NAME
``compositing``), the CPU model beside the figures.
"""

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import torch

from nerfexp import kernels
from nerfexp.files import atomic_write
from nerfexp.nerf.compositing import KERNEL, rendered
from nerfexp.rundir.layout import machine

RESULTS = Path(__file__).parent / "results"


def inputs(B: int, S: int) -> dict[str, torch.Tensor]:
    """Rays' samples as a step has them: densities with exact zeros (empty cells), sorted t in [2, 6]."""
    g = torch.Generator().manual_seed(0)
    sigmas = torch.rand(B, S, generator=g) * 3
    sigmas[torch.rand(B, S, generator=g) < 0.5] = 0
    t = (2 + 4 * torch.rand(B, S, generator=g)).sort(-1).values
    ends = torch.cat([t[:, 1:], torch.full((B, 1), 6.0)], -1)
    return {"sigmas": sigmas, "rgbs": torch.rand(B, S, 3, generator=g), "starts": t, "ends": ends, "t": t,
            "background": torch.ones(3)}


def step(data: dict[str, torch.Tensor]) -> tuple[torch.Tensor, ...]:
    """One forward and backward of ``rendered`` (a loss on the colour, as training's); the outputs and gradients."""
    sigmas, rgbs = data["sigmas"].clone().requires_grad_(), data["rgbs"].clone().requires_grad_()
    weights, out = rendered(sigmas, rgbs, data["starts"], data["ends"], data["t"], data["background"], far=6.0)
    out["rgb"].square().sum().backward()
    return weights.detach(), out["rgb"].detach(), sigmas.grad, rgbs.grad


def timed(data: dict[str, torch.Tensor], repeats: int) -> float:
    """Median seconds of one ``step`` over ``repeats``, after 20 not timed."""
    for _ in range(20):
        step(data)
    seconds = []
    for _ in range(repeats):
        started = time.perf_counter()
        step(data)
        seconds.append(time.perf_counter() - started)
    return statistics.median(seconds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rays", type=int, default=256)
    parser.add_argument("--samples", type=int, nargs="+", default=[24, 72, 96])
    parser.add_argument("--repeats", type=int, default=200)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--out", default="compositing")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if kernels.kernel(KERNEL) is None:
        raise SystemExit("the composite kernel was not built here (a C++ compiler and ninja): nothing to compare")
    rows = []
    for S in args.samples:
        data = inputs(args.rays, S)
        os.environ[kernels.SWITCH] = "on"
        fused_out = step(data)
        fused_s = timed(data, args.repeats)
        os.environ[kernels.SWITCH] = "off"
        torch_out = step(data)
        torch_s = timed(data, args.repeats)
        for mine, theirs in zip(fused_out, torch_out, strict=True):
            torch.testing.assert_close(mine, theirs, atol=2e-5, rtol=2e-5)
        rows.append({"rays": args.rays, "samples": S, "kernel_ms": 1e3 * fused_s, "torch_ms": 1e3 * torch_s,
                     "speedup": torch_s / fused_s})
        print(f"{args.rays} x {S}: kernel {1e3 * fused_s:.3f} ms, torch path {1e3 * torch_s:.3f} ms", flush=True)
    where = machine()["device"]
    out = RESULTS / args.out
    atomic_write(out.with_suffix(".json"), json.dumps({"machine": where, "repeats": args.repeats, "rows": rows},
                                                      indent=1).encode() + b"\n")
    lines = ["One forward and backward of the compositing (weights, colour, opacity, depth; gradients of the densities "
             "and colours), float32, median of "
             f"{args.repeats} after a warm-up, on {where}.", "",
             "| rays x samples | kernel (ms) | torch path (ms) | torch path / kernel |", "|---|---|---|---|"]
    lines += [f"| {r['rays']} x {r['samples']} | {r['kernel_ms']:.3f} | {r['torch_ms']:.3f} | {r['speedup']:.1f}x |"
              for r in rows]
    lines += ["", f"Command: `python benchmarks/compositing.py {' '.join(sys.argv[1:])}`".rstrip()]
    atomic_write(out.with_suffix(".md"), ("\n".join(lines) + "\n").encode())


if __name__ == "__main__":
    main()
