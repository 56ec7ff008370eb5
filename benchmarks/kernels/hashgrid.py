"""The hash grid encoding on a CPU: which formulation of its gathers is fast, against the positional
encoding's MLP that it replaces. Writes benchmarks/results/hashgrid.{json,md}.

One forward and backward pass (to the tables; sample positions need none) of the encoding at ``--points`` points (the
default is a ``scale=cpu`` training batch: 256 rays x 96 samples), with the sizes of ``encoding=hashgrid``
at ``scale=cpu`` (16 levels of 2 features, 2^16 entries, 16 to 256 cells), the median of ``--repeats``
after a warm-up, for each formulation:
- ``per_corner``: a gather per level and corner (``index_select``), the first thing one writes;
- ``embedding_bag``: all levels' 8 corners by ``F.embedding_bag`` with the trilinear weights as
  per-sample weights (one fused gather and weighted sum);
- ``one_gather``: all levels' corners in one ``index_select``, weights applied by one batched product;
  autograd's backward of ``index_select`` is a scatter-add;
- ``nerfexp``: ``HashGridEncoding`` as it runs: its fused C++ kernel where it was built (``nerfexp.kernels``,
  docs/acceleration.md);
- ``nerfexp_torch_path``: the same with ``NERFEXP_KERNELS=off``: dense levels by ``F.grid_sample``, the hashed ones
  corner-first ([8, L, N]) by one autograd node whose backward sums rows by one ``bincount``
  (``nerfexp.nerf.hashgrid.interpolate_rows``).
The reference: ``PositionalEncoding(10)`` followed by the 4 x 128 MLP of ``scale=cpu`` (the encoding
and the network it feeds, since the positional encoding alone costs nothing). The hash grid's own MLP
(one layer of 64) is timed with it. Every formulation is checked against ``nerfexp``'s output first.

    python benchmarks/kernels/hashgrid.py [--points 24576] [--repeats 10] [--threads N]
"""

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from nerfexp.files import atomic_write
from nerfexp.kernels import SWITCH
from nerfexp.nerf import hashgrid
from nerfexp.nerf.encodings import PositionalEncoding
from nerfexp.nerf.hashgrid import HASH_PRIMES, HashGridEncoding, interpolate_rows

OUT = Path(__file__).parents[1] / "results"  # benchmarks/results
CORNERS = torch.tensor([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)])  # [8, 3]: (i, j, k) offsets


def flat_table(enc: HashGridEncoding) -> tuple[nn.Parameter, list[int]]:
    """Every level's entries in one [R, F] table (dense levels flattened in (i, j, k) order), and each
    level's first row."""
    parts = [v[0].permute(1, 2, 3, 0).reshape(-1, enc.features_per_level) for v in enc.dense]
    parts += list(enc.hashed)
    starts = torch.tensor([0] + [len(p) for p in parts]).cumsum(0)[:-1].tolist()
    return nn.Parameter(torch.cat(parts).detach().clone()), starts


def corner_rows(enc: HashGridEncoding, points: torch.Tensor, starts: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows [N, L, 8] of the flat table and trilinear weights [N, L, 8] of every level's 8 corners of
    points [N, 3] in the box [-1, 1]^3."""
    unit = (points + 1) / 2
    rows, weights = [], []
    primes = torch.tensor(HASH_PRIMES)
    for level, n in enumerate(enc.resolutions):
        scaled = unit * n
        lower = scaled.floor().clamp(max=n - 1)
        frac = scaled - lower
        vertices = lower.long()[:, None, :] + CORNERS  # [N, 8, 3]
        if level < len(enc.dense):
            row = (vertices[..., 0] * (n + 1) + vertices[..., 1]) * (n + 1) + vertices[..., 2]
        else:
            hashed = vertices * primes
            row = (hashed[..., 0] ^ hashed[..., 1] ^ hashed[..., 2]) & (enc.table_size - 1)
        rows.append(row + starts[level])
        weights.append(torch.where(CORNERS.bool(), frac[:, None, :], 1 - frac[:, None, :]).prod(-1))
    return torch.stack(rows, 1), torch.stack(weights, 1)


def per_corner(table, enc, points, starts):
    rows, weights = corner_rows(enc, points, starts)
    out = 0
    for corner in range(8):
        values = table.index_select(0, rows[:, :, corner].flatten()).view(*rows.shape[:2], -1)  # [N, L, F]
        out = out + values * weights[..., corner, None]
    return out.flatten(1)


def embedding_bag(table, enc, points, starts):
    rows, weights = corner_rows(enc, points, starts)
    n, levels, _ = rows.shape
    return F.embedding_bag(rows.view(-1, 8), table, per_sample_weights=weights.view(-1, 8), mode="sum").view(n, -1)


def one_gather(table, enc, points, starts):
    rows, weights = corner_rows(enc, points, starts)
    values = table.index_select(0, rows.flatten()).view(*rows.shape, -1)  # [N, L, 8, F]
    return (weights[..., None, :] @ values).squeeze(-2).flatten(1)


def scatter_ms(enc: HashGridEncoding, points: torch.Tensor, repeats: int) -> dict[str, float]:
    """The hashed levels' backward sums (gradients per table entry) by ``bincount`` (nerfexp's,
    ``entry_sums``) and by ``index_add_``, on the entries the encoding reads for ``points``, in its order."""
    captured = {}

    def capture(table, corners, weights, sparse=False):
        captured["corners"] = corners
        return interpolate_rows(table, corners, weights, sparse)

    hashgrid.interpolate_rows = capture
    os.environ[SWITCH] = "off"  # the torch path's gathers (the fused kernel has none to capture)
    try:
        with torch.no_grad():
            enc(points)
    finally:
        hashgrid.interpolate_rows = interpolate_rows
        os.environ.pop(SWITCH)
    n_entries = enc.hashed.numel()
    entries = hashgrid.flat_indices(captured["corners"], n_entries // enc.features_per_level,
                                   enc.features_per_level).view(-1)
    values = torch.randn(len(entries))
    sums = {"bincount": lambda: hashgrid.entry_sums(entries, values, n_entries),
            "index_add_": lambda: values.new_zeros(n_entries).index_add_(0, entries, values)}
    torch.testing.assert_close(sums["bincount"](), sums["index_add_"](), rtol=1e-4, atol=1e-4)
    return {name: median_ms(fn, repeats) for name, fn in sums.items()}


def median_ms(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, default=256 * 96)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    box = [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]
    enc = HashGridEncoding(n_levels=16, features_per_level=2, log2_table_size=16, coarsest=16, finest=256, aabb=box)
    points = torch.rand(args.points, 3) * 2 - 1  # no gradient to positions, as in training
    table, starts = flat_table(enc)
    expected = enc(points).detach()
    mlp_hash = nn.Sequential(nn.Linear(enc.out_dim, 64), nn.ReLU(), nn.Linear(64, 16))
    posenc = PositionalEncoding(10)
    hidden = [m for _ in range(3) for m in (nn.Linear(128, 128), nn.ReLU())]
    mlp_posenc = nn.Sequential(nn.Linear(63, 128), nn.ReLU(), *hidden, nn.Linear(128, 16))
    timings = {}

    def step(features: torch.Tensor, mlp: nn.Module) -> None:
        mlp(features).square().sum().backward()

    for name, formulation in (("per_corner", per_corner), ("embedding_bag", embedding_bag),
                              ("one_gather", one_gather)):
        error = (formulation(table, enc, points, starts) - expected).abs().max().item()
        assert error < 1e-5, (name, error)  # the same encoding, up to rounding
        timings[name] = median_ms(lambda f=formulation: step(f(table, enc, points, starts), mlp_hash), args.repeats)
    timings["nerfexp"] = median_ms(lambda: step(enc(points), mlp_hash), args.repeats)  # its fused kernel, if built
    os.environ[SWITCH] = "off"
    timings["nerfexp_torch_path"] = median_ms(lambda: step(enc(points), mlp_hash), args.repeats)
    os.environ.pop(SWITCH)
    scatter = scatter_ms(enc, points, args.repeats)
    timings["posenc_mlp_4x128"] = median_ms(lambda: step(posenc(points), mlp_posenc), args.repeats)
    reference = timings["posenc_mlp_4x128"]
    machine = {"cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
               "processor": platform.processor() or platform.machine(), "torch": torch.__version__}
    report = {"points": args.points, "repeats": args.repeats, "machine": machine,
              "forward_backward_ms": {k: round(v, 2) for k, v in timings.items()},
              "relative_to_posenc_mlp": {k: round(v / reference, 2) for k, v in timings.items()},
              "backward_sums_ms": {k: round(v, 2) for k, v in scatter.items()}}
    lines = [f"Forward and backward at {args.points} points (median of {args.repeats}); ratio to the positional "
             "encoding with its 4 x 128 MLP.", "", "| formulation | ms | ratio |", "|---|---|---|"]
    lines += [f"| {k} | {v:.1f} | {v / reference:.2f} |" for k, v in timings.items()]
    lines += ["", "The backward's sums per table entry of the hashed levels (the entries the batch read, in the "
              "encoding's order), ms: " + ", ".join(f"`{k}` {v:.1f}" for k, v in scatter.items()) + "."]
    lines += ["", f"Machine: {machine}. Command: `python benchmarks/kernels/hashgrid.py"
              + (f" --points {args.points}" if args.points != 256 * 96 else "")
              + (f" --threads {args.threads}" if args.threads else "") + "`."]
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write(args.out / "hashgrid.json", (json.dumps(report, indent=2) + "\n").encode())
    atomic_write(args.out / "hashgrid.md", ("\n".join(lines) + "\n").encode())
    print("\n".join(lines))


if __name__ == "__main__":
    main()
