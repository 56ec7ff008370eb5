"""Which tool to write nerfexp's fused CPU kernels with (issue 43): the hash encoding's forward and backward (to the
tables) written once each way, side by side on the same inputs, against today's torch path.

- ``torch``: ``HashGridEncoding`` as it is (dense levels by ``F.grid_sample``, hashed ones by one gather and one
  ``bincount``), the reference every other output and gradient is checked against first;
- ``torch_compile``: the same module through ``torch.compile`` (Inductor's CPU backend: C++ and OpenMP it
  generates and compiles itself), compile time left out (a warm-up);
- ``cpp``: a C++ extension built with ``torch.utils.cpp_extension.load_inline`` (cached by its source's hash),
  ``at::parallel_for`` over points in the forward and over levels in the backward (each level's rows its own,
  so no two threads add to one row: no atomics, no per-thread copies);
- ``numba``: the same loops as ``@njit(parallel=True)`` functions (``prange``), compiled by LLVM at first call;
- ``nerfexp_kernel``: ``HashGridEncoding`` as shipped, with the kernel chosen (``nerfexp.kernels``,
  hash_encoding.cpp: the ``cpp`` loops over the module's own tables, compiled -O3 without -march=native).

Every kernel reads one flat [R, F] table (the dense levels' vertices in (i, j, k) order, then the hashed levels)
and the unit positions [N, 3] (mapped into the box and clamped by torch, as the module does), and writes features
[N, L F]; its backward writes the table's dense gradient [R, F]. Sizes are ``encoding=hashgrid`` at ``scale=cpu``
(16 levels of 2 features, 2^16 entries, 16 to 256 cells); the default points are a ``scale=cpu`` training batch
(256 rays x 96 samples). Times are medians of ``--repeats`` after a warm-up, forward + backward, float32 (the
encoding runs outside autocast, so the bf16 column of the issue is the same code path here).

    python benchmarks/kernels/kernel_tools.py [--points 24576] [--repeats 20] [--threads N]

Writes ``benchmarks/results/kernel_tools.{json,md}`` with the CPU's model and flags.
"""

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import torch
from hashgrid import median_ms  # benchmarks/kernels/hashgrid.py
from precision import cpu_model  # benchmarks/kernels/precision.py: the CPU's model name
from torch import nn

from nerfexp.files import atomic_write
from nerfexp.kernels import SWITCH
from nerfexp.nerf.hashgrid import HASH_PRIMES, HashGridEncoding
from nerfexp.rundir.layout import machine

OUT = Path(__file__).parents[1] / "results"  # benchmarks/results

CPP = r"""
#include <torch/extension.h>
#include <ATen/Parallel.h>
#include <cmath>

namespace {
const int64_t P1 = 1, P2 = 2654435761LL, P3 = 805459861LL;

struct Corners { int64_t row[8]; float w[8]; };

inline void corners_of(const float* u, int64_t n, int64_t start, bool hashed, int64_t mask, Corners& c) {
  int64_t lo[3]; float fr[3];
  for (int a = 0; a < 3; ++a) {
    float s = u[a] * n, f = std::floor(s);
    if (f > n - 1) f = n - 1;
    lo[a] = (int64_t)f; fr[a] = s - f;
  }
  for (int k = 0; k < 8; ++k) {
    int64_t i = lo[0] + ((k >> 2) & 1), j = lo[1] + ((k >> 1) & 1), l = lo[2] + (k & 1);
    int64_t row = hashed ? (((i * P1) ^ (j * P2) ^ (l * P3)) & mask) : ((i * (n + 1) + j) * (n + 1) + l);
    c.row[k] = start + row;
    c.w[k] = (((k >> 2) & 1) ? fr[0] : 1 - fr[0]) * (((k >> 1) & 1) ? fr[1] : 1 - fr[1])
             * ((k & 1) ? fr[2] : 1 - fr[2]);
  }
}
}  // namespace

torch::Tensor hash_forward(torch::Tensor unit, torch::Tensor table, std::vector<int64_t> res,
                           std::vector<int64_t> starts, std::vector<int64_t> hashed, int64_t table_size) {
  const int64_t N = unit.size(0), F = table.size(1), L = res.size();
  auto out = torch::empty({N, L * F}, table.options());
  const float* u = unit.data_ptr<float>();
  const float* t = table.data_ptr<float>();
  float* o = out.data_ptr<float>();
  at::parallel_for(0, N, 512, [&](int64_t begin, int64_t end) {
    Corners c;
    for (int64_t p = begin; p < end; ++p)
      for (int64_t l = 0; l < L; ++l) {
        corners_of(u + 3 * p, res[l], starts[l], hashed[l], table_size - 1, c);
        for (int64_t f = 0; f < F; ++f) {
          float acc = 0;
          for (int k = 0; k < 8; ++k) acc += c.w[k] * t[c.row[k] * F + f];
          o[(p * L + l) * F + f] = acc;
        }
      }
  });
  return out;
}

torch::Tensor hash_backward(torch::Tensor unit, torch::Tensor grad, int64_t rows, std::vector<int64_t> res,
                            std::vector<int64_t> starts, std::vector<int64_t> hashed, int64_t table_size) {
  const int64_t N = unit.size(0), L = res.size(), F = grad.size(1) / L;
  auto out = torch::zeros({rows, F}, grad.options());
  const float* u = unit.data_ptr<float>();
  const float* g = grad.data_ptr<float>();
  float* o = out.data_ptr<float>();
  at::parallel_for(0, L, 1, [&](int64_t begin, int64_t end) {
    Corners c;
    for (int64_t l = begin; l < end; ++l)
      for (int64_t p = 0; p < N; ++p) {
        corners_of(u + 3 * p, res[l], starts[l], hashed[l], table_size - 1, c);
        for (int64_t f = 0; f < F; ++f) {
          float gv = g[(p * L + l) * F + f];
          for (int k = 0; k < 8; ++k) o[c.row[k] * F + f] += c.w[k] * gv;
        }
      }
  });
  return out;
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("hash_forward", &hash_forward);
  m.def("hash_backward", &hash_backward);
}
"""


def flat_table(enc: HashGridEncoding) -> tuple[torch.Tensor, list[int], list[int], list[int]]:
    """Every level's entries in one [R, F] table (dense levels in (i, j, k) order), each level's first row, its
    resolution and whether it is hashed."""
    parts = [v[0].permute(1, 2, 3, 0).reshape(-1, enc.features_per_level) for v in enc.dense]
    parts += list(enc.hashed)
    starts = torch.tensor([0] + [len(p) for p in parts]).cumsum(0)[:-1].tolist()
    hashed = [0] * len(enc.dense) + [1] * len(enc.hashed)
    return torch.cat(parts).detach().clone().contiguous(), starts, list(enc.resolutions), hashed


def numba_kernels():
    """The forward and backward as numba functions (imported here: numba is not one of nerfexp's dependencies)."""
    import numba

    p1, p2, p3 = (np.int64(p) for p in HASH_PRIMES)

    @numba.njit(inline="always")
    def corner(u, n, start, hashed, mask, k):
        """Corner k's row and weight (scalars only: an array made here would be allocated per corner)."""
        sx, sy, sz = np.float32(u[0] * n), np.float32(u[1] * n), np.float32(u[2] * n)
        fx, fy, fz = min(np.floor(sx), n - 1), min(np.floor(sy), n - 1), min(np.floor(sz), n - 1)
        bx, by, bz = (k >> 2) & 1, (k >> 1) & 1, k & 1
        i, j, m = np.int64(fx) + bx, np.int64(fy) + by, np.int64(fz) + bz
        row = (((i * p1) ^ (j * p2) ^ (m * p3)) & mask) if hashed else ((i * (n + 1) + j) * (n + 1) + m)
        wx = np.float32(sx - fx) if bx else np.float32(1 - (sx - fx))
        wy = np.float32(sy - fy) if by else np.float32(1 - (sy - fy))
        wz = np.float32(sz - fz) if bz else np.float32(1 - (sz - fz))
        return start + row, wx * wy * wz

    @numba.njit(parallel=True, fastmath=False)
    def forward(unit, table, res, starts, hashed, table_size):
        n_points, levels, features = unit.shape[0], res.shape[0], table.shape[1]
        out = np.empty((n_points, levels * features), np.float32)
        for p in numba.prange(n_points):
            for level in range(levels):
                for f in range(features):
                    out[p, level * features + f] = 0
                for k in range(8):
                    row, w = corner(unit[p], res[level], starts[level], hashed[level], table_size - 1, k)
                    for f in range(features):
                        out[p, level * features + f] += w * table[row, f]
        return out

    @numba.njit(parallel=True, fastmath=False)
    def backward(unit, grad, rows, res, starts, hashed, table_size):
        n_points, levels = unit.shape[0], res.shape[0]
        features = grad.shape[1] // levels
        out = np.zeros((rows, features), np.float32)
        for level in numba.prange(levels):
            for p in range(n_points):
                for k in range(8):
                    row, w = corner(unit[p], res[level], starts[level], hashed[level], table_size - 1, k)
                    for f in range(features):
                        out[row, f] += w * grad[p, level * features + f]
        return out

    return forward, backward


class Kernel(torch.autograd.Function):
    """A forward/backward pair over the flat table as one autograd node (no gradient to positions)."""

    @staticmethod
    def forward(ctx, unit, table, kernels, levels):
        ctx.save_for_backward(unit)
        ctx.kernels, ctx.levels, ctx.rows = kernels, levels, table.shape[0]
        return kernels[0](unit, table, *levels)

    @staticmethod
    def backward(ctx, grad):
        (unit,) = ctx.saved_tensors
        return None, ctx.kernels[1](unit, grad.contiguous(), ctx.rows, *ctx.levels), None, None


def cpp_kernels():
    from torch.utils.cpp_extension import load_inline
    module = load_inline("nerfexp_kernel_tools", CPP, extra_cflags=["-O3", "-march=native", "-fopenmp"],
                         extra_ldflags=["-fopenmp"], verbose=False)
    return module.hash_forward, module.hash_backward


def numba_adapter():
    forward, backward = numba_kernels()

    def fwd(unit, table, res, starts, hashed, table_size):
        return torch.from_numpy(forward(unit.numpy(), table.detach().numpy(), np.asarray(res), np.asarray(starts),
                                        np.asarray(hashed), table_size))

    def bwd(unit, grad, rows, res, starts, hashed, table_size):
        return torch.from_numpy(backward(unit.numpy(), grad.numpy(), rows, np.asarray(res), np.asarray(starts),
                                         np.asarray(hashed), table_size))
    return fwd, bwd


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, default=256 * 96)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    box = [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]
    enc = HashGridEncoding(n_levels=16, features_per_level=2, log2_table_size=16, coarsest=16, finest=256, aabb=box)
    with torch.no_grad():  # entries of the size training gives them, so the check below means something
        for p in enc.parameters():
            p.uniform_(-1, 1)
    points = torch.rand(args.points, 3) * 2 - 1
    unit = ((points + 1) / 2).clamp(0, 1).contiguous()
    probe = torch.randn(args.points, enc.out_dim)  # the gradient arriving at the features

    # the reference: the module's torch path, and its gradient mapped into the flat layout
    os.environ[SWITCH] = "off"
    expected = enc(points)
    expected.backward(probe)
    flat_grad = torch.cat([v.grad[0].permute(1, 2, 3, 0).reshape(-1, enc.features_per_level) for v in enc.dense]
                          + list(enc.hashed.grad))
    table, starts, res, hashed = flat_table(enc)
    levels = (res, starts, hashed, enc.table_size)
    results, compile_s = {}, {}

    def torch_step(module: nn.Module):
        for p in enc.parameters():
            p.grad = None
        module(points).backward(probe)

    results["torch"] = median_ms(lambda: torch_step(enc), args.repeats)
    started = time.perf_counter()
    compiled = torch.compile(enc)
    torch_step(compiled)
    compile_s["torch_compile"] = time.perf_counter() - started
    torch.testing.assert_close(compiled(points), expected, rtol=1e-5, atol=1e-5)
    results["torch_compile"] = median_ms(lambda: torch_step(compiled), args.repeats)

    os.environ[SWITCH] = "on"  # the module as nerfexp ships it: its fused kernel (hash_encoding.cpp)
    assert enc._fused_kernel(unit) is not None, "the kernel was not built"
    torch.testing.assert_close(enc(points), expected, rtol=1e-5, atol=1e-5)
    results["nerfexp_kernel"] = median_ms(lambda: torch_step(enc), args.repeats)

    for name, build in (("cpp", cpp_kernels), ("numba", numba_adapter)):
        started = time.perf_counter()
        pair = build()
        flat = table.clone().requires_grad_()
        features = Kernel.apply(unit, flat, pair, levels)
        features.backward(probe)
        compile_s[name] = time.perf_counter() - started
        torch.testing.assert_close(features, expected, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(flat.grad, flat_grad, rtol=1e-4, atol=1e-4)

        def step(pair=pair, flat=flat):
            flat.grad = None
            Kernel.apply(unit, flat, pair, levels).backward(probe)
        results[name] = median_ms(step, args.repeats)

    reference = results["torch"]
    record = {"points": args.points, "repeats": args.repeats, "cpu": cpu_model(), "machine": machine(),
              "threads": torch.get_num_threads(), "forward_backward_ms": results,
              "speedup_over_torch": {k: reference / v for k, v in results.items()}, "first_call_s": compile_s,
              "command": "python benchmarks/kernels/kernel_tools.py"
                         + (f" --threads {args.threads}" if args.threads else "")}
    lines = [f"# Kernel tools: the hash encoding's forward + backward at {args.points} points", "",
             f"`{record['command']}` on {record['cpu']}, {record['threads']} torch threads, float32, median of "
             f"{args.repeats} after a warm-up; outputs and table gradients checked against the torch path first.", "",
             "| tool | ms | speed-up over torch | first call (build, compile), s |", "|---|---|---|---|"]
    lines += [f"| {k} | {v:.2f} | {reference / v:.2f}x | {compile_s.get(k, 0):.1f} |" for k, v in results.items()]
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write(args.out / "kernel_tools.json", (json.dumps(record, indent=2) + "\n").encode())
    atomic_write(args.out / "kernel_tools.md", ("\n".join(lines) + "\n").encode())
    print("\n".join(lines))


if __name__ == "__main__":
    main()
