"""Input encodings for the field: each maps [..., in_dim] to [..., out_dim] and reports ``out_dim``."""

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from nerfexp.nerf.bounds import Bounded

HASH_PRIMES = (1, 2654435761, 805459861)  # Instant-NGP's, one per axis; 1 keeps neighbours along x together


class IdentityEncoding(nn.Module):
    """Raw coordinates, unchanged: the "No Pos. Encoding" ablation."""

    def __init__(self, in_dim: int = 3):
        super().__init__()
        self.in_dim = in_dim
        self.out_dim = in_dim

    def forward(self, x: Tensor) -> Tensor:
        return x


class PositionalEncoding(nn.Module):
    """gamma(p) = (p, sin(2^0 pi p), cos(2^0 pi p), ..., sin(2^(L-1) pi p), cos(2^(L-1) pi p)).

    Applied per coordinate, L = ``n_freqs``; the raw input comes first when ``include_input``.
    Output layout for x [..., D]: [x | sin(pi 2^k x_d) for k, d | cos(pi 2^k x_d) for k, d], so
    ``out_dim = D * (include_input + 2 L)``: 63 for positions with L = 10, 27 for directions with L = 4.
    ``input_scale`` s encodes s p instead of p (the raw input stays p): every frequency moves down
    log2(1/s) octaves. s = 1 is the paper's; a power of two keeps the range reduction below exact.

    Exact range reduction: sin(2^k pi x) = sin(pi r) with r = fmod(2^k x, 2). Scaling by a power of two
    and ``fmod`` are exact in floating point, so the phase is rounded once, in pi r with |pi r| < 2 pi,
    and every frequency of the float32 input is computed to about 1e-6 (``tests/nerf/test_encodings.py``).
    The textbook ``sin(2^k (pi x))`` rounds pi x first and multiplies that rounding by 2^k, an error that
    grows with k (docs/numerics.md, ``benchmarks/encoding_precision.py``).

    >>> PositionalEncoding(n_freqs=1)(torch.tensor([[0.5, 0.0, 0.0]]))[0, 3:6]  # sin(pi x)
    tensor([1., 0., 0.])
    """

    def __init__(self, n_freqs: int, in_dim: int = 3, include_input: bool = True, input_scale: float = 1.0):
        super().__init__()
        self.n_freqs, self.in_dim, self.include_input = n_freqs, in_dim, include_input
        self.out_dim = in_dim * (int(include_input) + 2 * n_freqs)
        self.register_buffer("powers", input_scale * 2.0 ** torch.arange(n_freqs), persistent=False)

    def forward(self, x: Tensor) -> Tensor:
        """x [..., D] -> [..., out_dim]."""
        scaled = (x[..., None, :] * self.powers[:, None].to(x.dtype)).flatten(-2)  # s 2^k x: [..., L * D]
        phase = torch.pi * torch.fmod(scaled, 2)  # same sine and cosine, |phase| < 2 pi
        parts = [x] if self.include_input else []
        return torch.cat(parts + [torch.sin(phase), torch.cos(phase)], dim=-1)


class _GatherRows(torch.autograd.Function):
    """rows [M] of a table [..., F] (flat indices into its leading dims, row-major) -> [M, F].

    The backward sums the gradients of repeated rows. Dense (``sparse=False``): ``row_sums`` over every
    row of the table. Sparse (``sparse=True``): a sparse COO gradient of the rows gathered, each once
    (``touched_row_sums``), with the table's leading dims as its sparse dims and F as its dense dim.
    """

    @staticmethod
    def forward(ctx, table: Tensor, rows: Tensor, sparse: bool) -> Tensor:
        ctx.save_for_backward(rows)
        ctx.table_shape = table.shape
        ctx.sparse = sparse
        return table.reshape(-1, table.shape[-1]).index_select(0, rows)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None, None]:
        (rows,) = ctx.saved_tensors
        if ctx.sparse:
            return touched_row_sums(rows, grad, ctx.table_shape), None, None
        return row_sums(rows, grad, math.prod(ctx.table_shape[:-1])).view(ctx.table_shape), None, None


def row_sums(rows: Tensor, grad: Tensor, n_rows: int) -> Tensor:
    """Gradients grad [M, F] of rows [M] summed into every row of a table of ``n_rows``: [n_rows, F], by
    one ``bincount`` per feature (on a CPU several times faster than ``index_select``'s scatter-add backward)."""
    columns = grad.T.contiguous()  # [F, M]
    sums = [torch.bincount(rows, weights=column, minlength=n_rows) for column in columns]
    return torch.stack(sums, -1).to(grad.dtype)


def touched_row_sums(rows: Tensor, grad: Tensor, table_shape: torch.Size) -> Tensor:
    """Gradients grad [M, F] of rows [M] (flat indices into ``table_shape``'s leading dims) summed per
    row, as a sparse COO tensor of ``table_shape`` [..., F] (hybrid: the leading dims sparse) holding each
    row read once, in ascending order (coalesced; autograd's accumulation drops the flag, not the order).

    Whichever is cheaper: a table of at most M rows is summed whole (``row_sums``) and its rows read picked
    out (a count per row, O(M + rows)); a larger one by sorting the rows read (``torch.unique``,
    O(M log M)), whatever its size."""
    n_rows = math.prod(table_shape[:-1])
    if n_rows <= len(rows):
        touched = torch.bincount(rows, minlength=n_rows).nonzero().squeeze(1)  # [U] ascending
        sums = row_sums(rows, grad, n_rows).index_select(0, touched)  # [U, F]
    else:
        touched, slot = torch.unique(rows, sorted=True, return_inverse=True)  # [U] ascending, [M] into it
        sums = grad.new_zeros(len(touched), grad.shape[-1]).index_add_(0, slot, grad)  # [U, F]
    indices = torch.stack(torch.unravel_index(touched, table_shape[:-1]))  # [S, U], lexicographic order
    return torch.sparse_coo_tensor(indices, sums, table_shape, is_coalesced=True, check_invariants=False)


def gather_rows(table: Tensor, rows: Tensor, sparse: bool = False) -> Tensor:
    """table [..., F] at rows [M] (int64, flat indices into its leading dims) -> [M, F], differentiable
    in ``table``: a dense gradient, or with ``sparse`` a sparse one of the rows gathered (``_GatherRows``)."""
    return _GatherRows.apply(table, rows, sparse)


def level_resolutions(n_levels: int, coarsest: int, finest: int) -> list[int]:
    """Cells per side of each level: N_l = floor(N_min b^l) with b = exp((ln N_max - ln N_min) / (L - 1)),
    so that level 0 has ``coarsest`` and level L - 1 ``finest`` (Instant-NGP, eq. 2 and 3), computed
    exactly.

    >>> level_resolutions(3, 16, 64)
    [16, 32, 64]
    """
    if n_levels == 1:
        return [coarsest]
    k = n_levels - 1
    resolutions = []
    for level in range(n_levels):
        # exactly, in integers: the largest n with n^k <= N_min^(k - l) N_max^l (floating point puts
        # 3 * 8^(2/3) at 11.999..., whose floor would drop a cell)
        bound = coarsest ** (k - level) * finest**level
        n = math.floor(coarsest * (finest / coarsest) ** (level / k))  # within one of the answer
        while (n + 1) ** k <= bound:
            n += 1
        while n**k > bound:
            n -= 1
        resolutions.append(n)
    return resolutions


class HashGridEncoding(Bounded):
    """The multiresolution hash encoding of Instant-NGP (Mueller et al. 2022): positions [..., 3] ->
    trainable features [..., L F] (and the raw position first, with ``include_input``).

    Level l is a grid of N_l cells per side over the box ``aabb`` (``level_resolutions``: ``coarsest`` to
    ``finest`` in ``n_levels`` geometric steps); its (N_l + 1)^3 vertices hold ``features_per_level`` (F)
    features each. A level whose vertices fit the table, (N_l + 1)^3 <= T = 2^``log2_table_size``, stores
    them densely, one entry per vertex; a finer level maps them into a table of T entries with
    Instant-NGP's spatial hash, (i p_1 xor j p_2 xor k p_3) mod T with ``HASH_PRIMES``, colliding
    vertices sharing an entry. A position's features at a level are the
    trilinear interpolation of its cell's 8 vertices. Positions are mapped into the box and clamped to it:
    a point outside takes the features of the nearest point on the box (the raw input, with
    ``include_input``, lets the network tell them apart). Entries start uniform in +-``init_range``.

    The fast formulation on a CPU (``benchmarks/hashgrid.py`` says what was tried): dense levels are
    ``F.grid_sample`` volumes [1, F, N+1, N+1, N+1] (trilinear, fused forward and backward kernels);
    the hashed levels share one [L_h, T, F] table, read with one gather of all 8 corners of every level
    (``gather_rows``: its backward sums repeated rows by ``bincount``), and interpolated by one batched
    product of the weights [.., 1, 8] with the corners [.., 8, F].

    Layout: ``dense`` is a ParameterList of the dense levels (coarsest first), ``hashed`` the [L_h, T, F]
    table of the others; the output follows the levels in order.

    ``sparse_gradients``: the hashed table's gradient is a sparse COO tensor of the rows the batch read
    (sparse dims level and row, dense dim F; coalesced), so that an optimizer that takes one
    (``nerfexp.training.optimizers.LazyAdam``) reads and updates those rows only, whatever T; the dense
    levels keep dense gradients. torch.optim.Adam refuses sparse gradients.
    """

    def __init__(self, n_levels: int = 16, features_per_level: int = 2, log2_table_size: int = 19,
                 coarsest: int = 16, finest: int = 2048, include_input: bool = False, init_range: float = 1e-4,
                 aabb: Sequence[Sequence[float]] | None = None, sparse_gradients: bool = False):
        values = {"n_levels": n_levels, "features_per_level": features_per_level, "log2_table_size": log2_table_size,
                  "coarsest": coarsest, "finest": finest, "init_range": init_range}
        checks = {"n_levels": n_levels >= 1, "features_per_level": features_per_level >= 1,
                  "log2_table_size": 1 <= log2_table_size <= 30, "coarsest": coarsest >= 1,
                  "finest": coarsest <= finest < 2**20, "init_range": init_range > 0}
        bad = [key for key, ok in checks.items() if not ok]
        if bad:
            raise ValueError(f"encoding.position.{bad[0]}: expected n_levels >= 1, features_per_level >= 1, "
                             "1 <= log2_table_size <= 30, coarsest >= 1, coarsest <= finest < 2^20, init_range > 0; "
                             f"got {bad[0]}={values[bad[0]]}")
        super().__init__(aabb)
        self.in_dim = 3
        self.include_input = include_input
        self.sparse_gradients = sparse_gradients
        self.features_per_level = features_per_level
        self.table_size = 2**log2_table_size
        self.resolutions = level_resolutions(n_levels, coarsest, finest)
        self.out_dim = 3 * int(include_input) + n_levels * features_per_level
        dense = [n for n in self.resolutions if (n + 1) ** 3 <= self.table_size]
        hashed = self.resolutions[len(dense):]
        self.dense = nn.ParameterList(
            nn.Parameter(torch.empty(1, features_per_level, n + 1, n + 1, n + 1).uniform_(-init_range, init_range))
            for n in dense)
        self.hashed = nn.Parameter(torch.empty(len(hashed), self.table_size, features_per_level)
                                   .uniform_(-init_range, init_range))
        self.register_buffer("hashed_resolutions", torch.tensor(hashed, dtype=torch.float32), persistent=False)
        # the hash's constants, built once and moved with the module (not saved: checkpoints keep their keys)
        self.register_buffer("hash_primes", torch.tensor(HASH_PRIMES), persistent=False)  # [3] int64
        self.register_buffer("level_offsets", self.table_size * torch.arange(len(hashed))[:, None],
                             persistent=False)  # [L_h, 1]: the first row of each level in the flat table

    def forward(self, x: Tensor) -> Tensor:
        """x [..., 3] -> [..., out_dim] in the table's dtype (float32 in training), autocast or not.

        The lookups and their interpolation are gather- and scatter-bound, not matrix products: under
        bf16 autocast they would only add casts of the gathered corners (and round the table's
        features to 8 bits), so they run in the table's precision; the network after them autocasts."""
        self.require_bounds()
        with torch.autocast(x.device.type, enabled=False):
            return self._features(x.to(self.hashed.dtype))

    def _features(self, x: Tensor) -> Tensor:
        """``forward`` outside autocast."""
        points = x.reshape(-1, 3)
        unit = ((points - self.aabb[0]) / (self.aabb[1] - self.aabb[0])).clamp(0, 1)  # [N, 3]
        parts = [points] if self.include_input else []
        grid = (2 * unit - 1).view(1, -1, 1, 1, 3).flip(-1)  # grid_sample reads (x, y, z) as (k, j, i)
        for volume in self.dense:  # [1, F, N+1, N+1, N+1], indexed [i, j, k]
            parts.append(F.grid_sample(volume, grid, mode="bilinear", align_corners=True).view(volume.shape[1], -1).T)
        if len(self.hashed):
            parts.append(self._hashed_features(unit).flatten(1))
        return torch.cat(parts, -1).view(*x.shape[:-1], self.out_dim)

    def _hashed_features(self, unit: Tensor) -> Tensor:
        """unit positions [N, 3] in [0, 1] -> interpolated features of the hashed levels [N, L_h, F]."""
        _, table_size, n_features = self.hashed.shape
        scaled = unit[:, None, :] * self.hashed_resolutions[:, None].to(unit.dtype)  # [N, L_h, 3]
        lower = scaled.floor().clamp(max=self.hashed_resolutions[:, None].to(unit.dtype) - 1)  # 1 -> the last cell
        frac = scaled - lower
        vertices = lower.long()
        # hashed per axis, then combined: (a xor b) mod 2^n = (a mod 2^n) xor (b mod 2^n); int64 products of
        # vertices below 2^20 cannot overflow
        corner_pairs = torch.stack([vertices, vertices + 1], -1)  # [N, L_h, 3, 2]
        rows = (corner_pairs * self.hash_primes[:, None]) & (table_size - 1)  # [N, L_h, 3, 2]
        rx, ry, rz = rows.unbind(-2)  # [N, L_h, 2]: the lower and upper vertex along each axis
        corners = (rx[..., :, None, None] ^ ry[..., None, :, None] ^ rz[..., None, None, :]).flatten(-3)  # [N, L_h, 8]
        corners = corners + self.level_offsets  # rows of the flat table
        linear = torch.stack([1 - frac, frac], -1)  # [N, L_h, 3, 2]: weights of the lower and upper vertex
        wx, wy, wz = linear.unbind(-2)
        weights = (wx[..., :, None, None] * wy[..., None, :, None] * wz[..., None, None, :]).flatten(-3)
        values = gather_rows(self.hashed, corners.flatten(), sparse=self.sparse_gradients)  # [N L_h 8, F]
        return (weights[..., None, :] @ values.view(*corners.shape, n_features)).squeeze(-2)  # [N, L_h, F]
