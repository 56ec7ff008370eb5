"""The hash grid encoding's independent truth, shared by its tests (test_hashgrid, test_hash_kernel): a float64
reference written from the paper's definition (Python integers for the hash, explicit loops over the 8 corners),
and a small encoding over a box of unequal sides."""

import itertools
import math

import torch

from nerfexp.nerf.hashgrid import HASH_PRIMES, HashGridEncoding

BOX = [[-1.0, -0.5, 0.0], [1.0, 1.5, 3.0]]  # unequal sides: the axes must not be mixed up


def reference_features(enc: HashGridEncoding, points: torch.Tensor) -> torch.Tensor:
    """The encoding of points [N, 3] computed one point, one level, one corner at a time in float64."""
    lo, hi = torch.tensor(BOX, dtype=torch.float64)
    out = []
    for p in points.double():
        unit = ((p - lo) / (hi - lo)).clamp(0, 1).tolist()
        features = []
        for level, n in enumerate(enc.resolutions):
            cell = [min(math.floor(u * n), n - 1) for u in unit]
            frac = [u * n - c for u, c in zip(unit, cell, strict=True)]
            value = torch.zeros(enc.features_per_level, dtype=torch.float64)
            for corner in itertools.product((0, 1), repeat=3):
                vertex = [c + o for c, o in zip(cell, corner, strict=True)]
                weight = math.prod(f if o else 1 - f for f, o in zip(frac, corner, strict=True))
                value += weight * entry(enc, level, vertex)
            features.append(value)
        out.append(torch.cat(features))
    return torch.stack(out)


def entry(enc: HashGridEncoding, level: int, vertex: list[int]) -> torch.Tensor:
    """The features [F] the encoding stores for integer ``vertex`` (i, j, k) of ``level``."""
    if level < len(enc.dense):
        i, j, k = vertex
        return enc.dense[level][0, :, i, j, k].double()
    return enc.hashed[hashed_row(enc, level, vertex)].double()


def hashed_row(enc: HashGridEncoding, level: int, vertex: list[int]) -> tuple[int, int]:
    """Where a hashed ``level`` stores ``vertex``: (its index among the hashed levels, its row in the table)."""
    row = 0
    for v, prime in zip(vertex, HASH_PRIMES, strict=True):
        row ^= v * prime  # Python integers: no overflow, no masking before the end
    return level - len(enc.dense), row % enc.table_size


def small_encoding(**kwargs) -> HashGridEncoding:
    torch.manual_seed(0)
    settings = dict(n_levels=4, features_per_level=2, log2_table_size=10, coarsest=3, finest=24, aabb=BOX,
                    init_range=1.0)
    return HashGridEncoding(**(settings | kwargs))
