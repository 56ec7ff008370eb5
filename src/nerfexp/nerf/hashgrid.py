"""Instant-NGP's multiresolution hash encoding (Mueller et al. 2022), ``HashGridEncoding``: its torch path
(dense levels by ``F.grid_sample``, hashed ones by one gather and one ``bincount``, ``interpolate_rows``) and the
bridge to its fused CPU kernel (``nerfexp.kernels``, hash_encoding.cpp: ``_FusedHashEncoding``, ``PassGradients``).
An ``Encoding`` (``nerfexp.nerf.encodings``) like the others."""

import math
import weakref
from collections.abc import Mapping, Sequence
from typing import ClassVar

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from nerfexp.domains import BOOLEAN, COUNT, Consistent, Memory, whole
from nerfexp.kernels import kernel
from nerfexp.nerf.bounds import Bounded
from nerfexp.nerf.encodings import Encoding
from nerfexp.sizes import hash_table_bytes

HASH_PRIMES = (1, 2654435761, 805459861)  # Instant-NGP's, one per axis; 1 keeps neighbours along x together
HASH_MAX_LOG2_TABLE_SIZE = 30  # a level's table at most 2^30 rows, the encoding's own limit
HASH_RESOLUTION_LIMIT = 2 ** 20  # resolutions below it: a cell's integer corner times a prime stays within int64


class _InterpolateRows(torch.autograd.Function):
    """Weighted sums of table rows: table [..., F], corner rows corners [C, *B] (flat indices into the
    table's leading dims, row-major), weights [C, *B] -> [*B, F], sum over c of weights[c] table[corners[c]];
    differentiable in ``table`` only.

    Laid out feature- and corner-first ([F, C, *B]) so that every elementwise step runs along the
    contiguous batch dims, and the table is read in place by flat entry indices (``flat_indices``). The
    backward sums each entry's weighted gradients: dense (``sparse=False``) by ``entry_sums`` over the
    flat table; sparse (``sparse=True``) as a sparse COO gradient of the rows read, each once
    (``touched_row_sums``), with the table's leading dims as its sparse dims and F as its dense dim.
    """

    @staticmethod
    def forward(ctx, table: Tensor, corners: Tensor, weights: Tensor, sparse: bool) -> Tensor:
        entries = flat_indices(corners, math.prod(table.shape[:-1]), table.shape[-1])  # [F, C, *B]
        ctx.save_for_backward(corners if sparse else entries, weights)  # what each backward reads
        ctx.table_shape = table.shape
        ctx.sparse = sparse
        values = table.reshape(-1).index_select(0, entries.view(-1)).view(entries.shape)
        return (values * weights).sum(1).movedim(0, -1)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None, None, None]:
        indices, weights = ctx.saved_tensors  # corners [C, *B] where sparse, else entries [F, C, *B]
        columns = weights * grad.movedim(-1, 0).contiguous()[:, None]  # [F, C, *B]
        if ctx.sparse:
            return touched_row_sums(indices.reshape(-1), columns.flatten(1), ctx.table_shape), None, None, None
        return entry_sums(indices, columns, math.prod(ctx.table_shape)).view(ctx.table_shape), None, None, None


class _FusedHashEncoding(torch.autograd.Function):
    """``HashGridEncoding``'s features of unit positions [N, 3] by the fused kernel (``nerfexp.kernels``,
    hash_encoding.cpp): forward [N, L F]; backward the gradients of each dense volume [1, F, n+1, n+1, n+1] (dense)
    and of the hashed table [L_h, T, F]: dense, summed over the calls of one backward pass in one set of tensors
    (``PassGradients``), or with ``sparse`` the coalesced sparse COO tensor of the rows read (as
    ``touched_row_sums`` makes it); none to the positions."""

    @staticmethod
    def forward(ctx, unit: Tensor, fused, shape: tuple, sparse: bool, sums: "PassGradients", hashed: Tensor,
                *dense: Tensor) -> Tensor:
        ctx.save_for_backward(unit, hashed, *dense)
        ctx.fused, ctx.shape, ctx.sparse, ctx.sums = fused, shape, sparse, sums  # shape: HashGridEncoding.kernel_shape()
        return fused.forward(unit, [volume[0] for volume in dense], hashed, *ctx.shape)

    @staticmethod
    def backward(ctx, grad: Tensor):
        unit, hashed, *dense = ctx.saved_tensors
        volumes = [volume[0] for volume in dense]
        if ctx.sparse:
            *dense_grads, indices, values = ctx.fused.backward_rows(unit, grad.contiguous(), volumes, hashed,
                                                                    *ctx.shape)
            hashed_grad = torch.sparse_coo_tensor(indices, values, hashed.shape, is_coalesced=True,
                                                  check_invariants=False)
            return None, None, None, None, None, hashed_grad, *(g[None] for g in dense_grads)
        if not all(ctx.needs_input_grad[5:]):  # a table without a gradient: no shared sums, a gradient of its own
            *dense_grads, hashed_grad = ctx.fused.backward(unit, grad.contiguous(), volumes, hashed, *ctx.shape)
            return None, None, None, None, None, hashed_grad, *(g[None] for g in dense_grads)
        (hashed_grad, *dense_grads), first = ctx.sums.of([hashed, *dense])
        ctx.fused.backward_into(unit, grad.contiguous(), [g[0] for g in dense_grads], hashed_grad, *ctx.shape)
        if not first:  # summed into the gradients an earlier call of this pass handed autograd
            return None, None, None, None, None, None, *(None for _ in dense)
        return None, None, None, None, None, hashed_grad, *dense_grads


class PassGradients:
    """Where one encoding's fused calls (``_FusedHashEncoding``) sum their tables' dense gradients in a backward
    pass: the pass's first call makes zero tensors and hands them to autograd as its gradients; the pass's later
    calls sum theirs into the same tensors and hand autograd none. Autograd reads a parameter's gradient once every
    node of the pass that feeds it has run, so it reads the sum of all the calls: one zero fill of the tables per
    pass, where one per call and autograd's sums of them took a large share of a small step (the renderer queries
    a network several times per step: ``VolumeRenderer._query``'s segments).

    A pass ends when autograd has a table's gradient, which it has only once every call of the pass has run: the
    pass's first call puts a hook on each table (``Tensor.register_hook``, which autograd runs in ``backward`` and
    ``torch.autograd.grad`` alike, before it stores or returns the gradient), and the first of them to run ends the
    pass; the next call starts new tensors (and takes the old hooks off). Every call of the encoding feeds every
    table that needs a gradient, so a pass that runs a call ends with a hook. The tensors are held weakly: they are
    autograd's, which takes them as the parameters' gradients without a copy where it holds the only reference;
    where they are gone, a call starts new ones (always correct: autograd then sums what each hands it). A copy or
    a pickle of the encoding starts empty. Two backward passes through one encoding at once (two threads) are not
    told apart."""

    def __init__(self):
        self._sums: list[weakref.ref] = []  # the pass in progress' tensors; empty between passes
        self._ends: list[torch.utils.hooks.RemovableHandle] = []  # the hooks its first call put on the tables

    def of(self, tables: list[Tensor]) -> tuple[list[Tensor], bool]:
        """Gradient tensors for ``tables`` (each of its table's shape) in this backward pass, and whether they are
        new (zeros, to be handed to autograd) rather than an earlier call's."""
        sums = [ref() for ref in self._sums]
        if len(sums) == len(tables) and all(s is not None for s in sums):
            return sums, False
        for handle in self._ends:  # an earlier pass's (a hook does not take itself off while autograd runs it)
            handle.remove()
        sums = [torch.zeros_like(table, memory_format=torch.contiguous_format) for table in tables]
        self._sums = [weakref.ref(s) for s in sums]
        self._ends = [table.register_hook(self._end) for table in tables]
        return sums, True

    def _end(self, grad: Tensor) -> None:
        """A table's gradient is complete: the pass's calls are done; the next call starts a new pass."""
        self._sums = []

    def __reduce__(self):
        return PassGradients, ()


def flat_indices(rows: Tensor, n_rows: int, n_features: int) -> Tensor:
    """Rows [*R] of a table [n_rows, F] -> the flat indices [F, *R] of their entries, r F + f (in int64
    where the table's entries pass int32's range)."""
    if n_rows * n_features > 2**31:
        rows = rows.long()
    features = torch.arange(n_features, dtype=rows.dtype, device=rows.device).view(-1, *[1] * rows.dim())
    return rows[None] * n_features + features


def entry_sums(entries: Tensor, values: Tensor, n_entries: int) -> Tensor:
    """values [*M] summed per flat table entry, entries [*M] -> [n_entries], by one ``bincount``
    (accumulated in float64, returned in the values' dtype). On a CPU as fast as ``index_add_`` at a
    full batch and faster at the occupancy grid's small packed ones (``benchmarks/kernels/hashgrid.py``)."""
    return torch.bincount(entries.reshape(-1), weights=values.reshape(-1), minlength=n_entries).to(values.dtype)


def row_sums(rows: Tensor, columns: Tensor, n_rows: int) -> Tensor:
    """Gradients columns [F, M] (one row of M values per feature) of rows [M] summed into every row of a
    table of ``n_rows``: [n_rows, F] (``entry_sums`` over ``flat_indices``)."""
    return entry_sums(flat_indices(rows, n_rows, len(columns)), columns, n_rows * len(columns)).view(n_rows, -1)


def touched_row_sums(rows: Tensor, columns: Tensor, table_shape: torch.Size) -> Tensor:
    """Gradients columns [F, M] of rows [M] (flat indices into ``table_shape``'s leading dims) summed per
    row, as a sparse COO tensor of ``table_shape`` [..., F] (hybrid: the leading dims sparse) holding each
    row read once, in ascending order (coalesced; autograd's accumulation drops the flag, not the order).

    Whichever is cheaper: a table of at most M rows is summed whole (``row_sums``) and its rows read picked
    out (a count per row, O(M + rows)); a larger one by sorting the rows read (``torch.unique``,
    O(M log M)), whatever its size."""
    n_rows = math.prod(table_shape[:-1])
    if n_rows <= len(rows):
        touched = torch.bincount(rows, minlength=n_rows).nonzero().squeeze(1)  # [U] ascending
        sums = row_sums(rows, columns, n_rows).index_select(0, touched)  # [U, F]
    else:
        touched, slot = torch.unique(rows, sorted=True, return_inverse=True)  # [U] ascending, [M] into it
        sums = columns.new_zeros(len(touched), len(columns)).index_add_(0, slot, columns.T)  # [U, F]
    indices = torch.stack(torch.unravel_index(touched.long(), table_shape[:-1]))  # [S, U], lexicographic order
    return torch.sparse_coo_tensor(indices, sums, table_shape, is_coalesced=True, check_invariants=False)


def interpolate_rows(table: Tensor, corners: Tensor, weights: Tensor, sparse: bool = False) -> Tensor:
    """table [..., F], corner rows [C, *B] (integer flat indices into its leading dims), weights [C, *B]
    -> [*B, F], the weighted sum of each batch entry's C rows, differentiable in ``table``: a dense
    gradient, or with ``sparse`` a sparse one of the rows read (``_InterpolateRows``).

    Weights that need a gradient (positions differentiated, as for normals from the density) take
    autograd's own gather and sum instead, differentiable in both and twice; the table's gradient is then
    dense."""
    if torch.is_grad_enabled() and weights.requires_grad:
        values = table.reshape(-1, table.shape[-1]).index_select(0, corners.reshape(-1))  # [C B, F]
        return (weights[..., None] * values.view(*corners.shape, -1)).sum(0)
    return _InterpolateRows.apply(table, corners, weights, sparse)


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


class HashGridEncoding(Bounded, Encoding):
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

    The fast formulation on a CPU (``benchmarks/kernels/hashgrid.py`` says what was tried): dense levels are
    ``F.grid_sample`` volumes [1, F, N+1, N+1, N+1] (trilinear, fused forward and backward kernels);
    the hashed levels share one [L_h, T, F] table, read for all 8 corners of every level at once and
    interpolated in one autograd node (``interpolate_rows``: one gather of every entry read; its backward
    sums repeated entries by one ``bincount``), corner-first so that the elementwise work runs along the points.

    Layout: ``dense`` is a ParameterList of the dense levels (coarsest first), ``hashed`` the [L_h, T, F]
    table of the others; the output follows the levels in order.

    ``sparse_gradients``: the hashed table's gradient is a sparse COO tensor of the rows the batch read
    (sparse dims level and row, dense dim F; coalesced), so that an optimizer that takes one
    (``nerfexp.training.optimizers.LazyAdam``) reads and updates those rows only, whatever T; the dense
    levels keep dense gradients. torch.optim.Adam refuses sparse gradients.
    """

    # Read by trainer.precision=auto (nerfexp.training.precision): its lookups and interpolation stay float32
    CPU_AUTOCAST_SLOWER: ClassVar[str] = ("bf16 autocast made a hash-grid step with the grid slower on a CPU "
                                          "(docs/precision.md)")

    DOMAINS = {
        "n_levels": COUNT,
        "features_per_level": COUNT,
        "log2_table_size": whole(1, HASH_MAX_LOG2_TABLE_SIZE),
        "coarsest": whole(1, HASH_RESOLUTION_LIMIT - 1),  # and <= finest (CONSISTENT)
        "finest": whole(1, HASH_RESOLUTION_LIMIT - 1),
        "include_input": BOOLEAN,
        "sparse_gradients": BOOLEAN,  # and an optimizer that takes them (SPARSE_GRADIENTS)
    }
    CONSISTENT: ClassVar[dict[tuple[str, ...], Consistent]] = {
        ("coarsest", "finest"): lambda config: (None if config["coarsest"] <= config["finest"] else
                                                "coarsest <= finest (the levels' resolutions go from one to the other)"),
    }
    SCENE_FIELDS: ClassVar[tuple[str, ...]] = ("aabb",)  # its levels span the scene's box

    @staticmethod
    def MEMORY(config: Mapping) -> list[Memory]:
        """Its tables and their optimizer state."""
        return [(("n_levels", "log2_table_size", "features_per_level"), f"a hash encoding of {config['n_levels']} levels",
                 hash_table_bytes(config["n_levels"], config["log2_table_size"], config["features_per_level"]))]

    @staticmethod
    def SPARSE_GRADIENTS(config: Mapping) -> list[str]:
        """``sparse_gradients`` where set: the table's gradients are sparse."""
        return ["sparse_gradients"] if config.get("sparse_gradients") else []

    def __init__(self, n_levels: int = 16, features_per_level: int = 2, log2_table_size: int = 19,
                 coarsest: int = 16, finest: int = 2048, include_input: bool = False, init_range: float = 1e-4,
                 aabb: Sequence[Sequence[float]] | None = None, sparse_gradients: bool = False):
        values = {"n_levels": n_levels, "features_per_level": features_per_level, "log2_table_size": log2_table_size,
                  "coarsest": coarsest, "finest": finest, "init_range": init_range}
        checks = {"n_levels": n_levels >= 1, "features_per_level": features_per_level >= 1,
                  "log2_table_size": 1 <= log2_table_size <= HASH_MAX_LOG2_TABLE_SIZE, "coarsest": coarsest >= 1,
                  "finest": coarsest <= finest < HASH_RESOLUTION_LIMIT, "init_range": init_range > 0}
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
        # corner rows in int32 where the flat table allows (narrower gathers and sums than int64): the
        # offsets' dtype is the rows'
        row_dtype = torch.int32 if len(hashed) * self.table_size <= 2**31 else torch.int64
        first_rows = self.table_size * torch.arange(len(hashed), dtype=row_dtype)[:, None]
        self.register_buffer("level_offsets", first_rows, persistent=False)  # [L_h, 1]: each level's first row
        self.pass_gradients = PassGradients()  # the fused kernel's dense gradients, summed per backward pass

    def kernel_shape(self) -> tuple[list[int], list[int], int]:
        """What the fused kernel needs besides the tables: the dense and the hashed levels' cells per side, and
        the features per level."""
        n_dense = len(self.dense)
        return list(self.resolutions[:n_dense]), list(self.resolutions[n_dense:]), self.features_per_level

    def parameter_groups(self) -> dict[str, dict]:
        """The tables, dense and hashed, in a group of their own without weight decay: Instant-NGP decays the
        networks' weights only, since most steps leave most table entries untouched, and decay would wipe out the
        ones rarely seen."""
        return {"hash_tables": {"params": list(self.parameters()), "weight_decay": 0.0}}

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
        fused = self._fused_kernel(unit)
        if fused is not None:
            parts.append(_FusedHashEncoding.apply(unit.contiguous(), fused, self.kernel_shape(), self.sparse_gradients,
                                                  self.pass_gradients, self.hashed, *self.dense))
            return torch.cat(parts, -1).view(*x.shape[:-1], self.out_dim)
        grid = (2 * unit - 1).view(1, -1, 1, 1, 3).flip(-1)  # grid_sample reads (x, y, z) as (k, j, i)
        for volume in self.dense:  # [1, F, N+1, N+1, N+1], indexed [i, j, k]
            parts.append(F.grid_sample(volume, grid, mode="bilinear", align_corners=True).view(volume.shape[1], -1).T)
        if len(self.hashed):
            parts.append(self._hashed_features(unit).flatten(1))
        return torch.cat(parts, -1).view(*x.shape[:-1], self.out_dim)

    def kernels(self) -> tuple[str, ...]:
        """hash_encoding where its tables are float32 on a CPU (``_fused_kernel``'s own condition on them)."""
        return ("hash_encoding",) if self.hashed.device.type == "cpu" and self.hashed.dtype == torch.float32 else ()

    def _fused_kernel(self, unit: Tensor):
        """The fused CPU kernel (``nerfexp.kernels``, hash_encoding.cpp) where it computes this forward and its
        backward: float32 on a CPU (the hashed table's gradient dense, or its rows read with ``sparse_gradients``),
        positions not differentiated (normals from the density take autograd's own path, differentiable twice), not
        traced by ``torch.compile`` (which compiles the torch path's operators itself, ``model.compile=true``);
        else None (the torch path, its reference)."""
        if (unit.device.type != "cpu" or self.hashed.dtype != torch.float32
                or (torch.is_grad_enabled() and unit.requires_grad) or torch.compiler.is_compiling()):
            return None
        return kernel("hash_encoding")

    def _hashed_features(self, unit: Tensor) -> Tensor:
        """unit positions [N, 3] in [0, 1] -> interpolated features of the hashed levels [N, L_h, F].

        Computed level- and corner-first ([2, L_h, 3, N], [8, L_h, N]): every broadcast then runs along the
        contiguous points (trailing dims of 2 or 8 made the elementwise kernels several times slower)."""
        table_size = self.hashed.shape[1]
        resolutions = self.hashed_resolutions.to(unit.dtype)[:, None, None]  # [L_h, 1, 1]
        scaled = unit.T * resolutions  # [L_h, 3, N]
        lower = scaled.floor().clamp(max=resolutions - 1)  # 1 -> the last cell
        frac = scaled - lower
        vertices = lower.long()
        # hashed per axis, then combined: (a xor b) mod 2^n = (a mod 2^n) xor (b mod 2^n); int64 products of
        # vertices below 2^20 cannot overflow
        corner_pairs = torch.stack([vertices, vertices + 1])  # [2, L_h, 3, N]: lower and upper vertex per axis
        rows = (corner_pairs * self.hash_primes[:, None]) & (table_size - 1)
        rx, ry, rz = rows.to(self.level_offsets.dtype).unbind(-2)  # [2, L_h, N]
        # each level's first row of the flat table, added to one axis: rows < T and the offsets are multiples
        # of T, so adding before the xor equals adding after
        rz = rz + self.level_offsets
        corners = (rx[:, None, None] ^ ry[None, :, None] ^ rz[None, None, :]).flatten(0, 2)  # [8, L_h, N]
        wx, wy, wz = torch.stack([1 - frac, frac]).unbind(-2)  # [2, L_h, N]: weights of the lower and upper vertex
        weights = (wx[:, None, None] * wy[None, :, None] * wz[None, None, :]).flatten(0, 2)  # [8, L_h, N]
        return interpolate_rows(self.hashed, corners, weights, sparse=self.sparse_gradients).transpose(0, 1)
