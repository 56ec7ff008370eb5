"""The hash grid encoding against independent truth: a float64 reference written from the paper's
definition (Python integers for the hash, explicit loops over the 8 corners), functions that trilinear
interpolation reproduces exactly, gradcheck in float64, and where collisions can and cannot happen."""

import functools
import itertools
import math

import pytest
import torch

from nerfexp.nerf.encodings import PositionalEncoding
from nerfexp.nerf.fields import MLPViewDependence, NeRFField
from nerfexp.nerf.hashgrid import HASH_PRIMES, HashGridEncoding, flat_indices, level_resolutions
from tests.nerf.hashgrid_reference import BOX, hashed_row, reference_features, small_encoding


def test_level_resolutions_grow_geometrically_from_coarsest_to_finest():
    assert level_resolutions(3, 16, 64) == [16, 32, 64]
    assert level_resolutions(1, 16, 2048) == [16]
    resolutions = level_resolutions(16, 16, 2048)  # Instant-NGP's: b = exp(ln(128) / 15) = 1.3819
    assert resolutions[0] == 16 and resolutions[-1] == 2048
    assert resolutions[1] == math.floor(16 * 128 ** (1 / 15))  # 22


def test_dense_and_hashed_levels_split_where_the_vertices_fit_the_table():
    enc = small_encoding()  # resolutions 3, 6, 12, 24; T = 1024: 4^3 and 7^3 fit, 13^3 = 2197 does not
    assert enc.resolutions == [3, 6, 12, 24]
    assert [tuple(v.shape) for v in enc.dense] == [(1, 2, 4, 4, 4), (1, 2, 7, 7, 7)]
    assert tuple(enc.hashed.shape) == (2, 1024, 2)
    assert enc.out_dim == 8 and small_encoding(include_input=True).out_dim == 11


@pytest.mark.parametrize("log2_table_size", [10, 4, 20])  # mixed; every level hashed; every level dense
def test_matches_the_float64_reference(log2_table_size, device):
    enc = small_encoding(log2_table_size=log2_table_size).double()
    generator = torch.Generator().manual_seed(1)
    inside = torch.rand(200, 3, generator=generator, dtype=torch.float64)
    lo, hi = torch.tensor(BOX, dtype=torch.float64)
    points = torch.cat([lo + inside * (hi - lo),
                        torch.stack([lo, hi, (lo + hi) / 2]),  # corners of the box, its centre
                        lo + torch.tensor([[1.5, 0.5, 0.5], [-0.2, 0.3, 1.0]], dtype=torch.float64) * (hi - lo)])
    expected = reference_features(enc, points)  # on the CPU
    torch.testing.assert_close(enc.to(device)(points.to(device)).cpu(), expected, atol=1e-12, rtol=0)


def test_linear_functions_are_interpolated_exactly_at_every_level():
    # Entries set to a*i + b*j + c*k at vertex (i, j, k): trilinear interpolation returns a linear function
    # exactly, a*u_x*N + b*u_y*N + c*u_z*N at unit position u, whatever the vertex layout.
    enc = small_encoding(log2_table_size=20, features_per_level=1).double()  # all levels dense
    a, b, c = 0.3, -1.1, 2.0
    with torch.no_grad():
        for volume in enc.dense:
            n = volume.shape[-1]
            i, j, k = torch.meshgrid(*[torch.arange(n, dtype=torch.float64)] * 3, indexing="ij")
            volume[0, 0] = a * i + b * j + c * k
    lo, hi = torch.tensor(BOX, dtype=torch.float64)
    unit = torch.rand(100, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    expected = torch.stack([(unit * n) @ torch.tensor([a, b, c], dtype=torch.float64) for n in enc.resolutions], -1)
    torch.testing.assert_close(enc(lo + unit * (hi - lo)), expected, atol=1e-12, rtol=0)


def test_no_collisions_in_dense_levels_and_collisions_above_them():
    enc = small_encoding(log2_table_size=10)
    for level, n in enumerate(enc.resolutions):
        vertices = list(itertools.product(range(n + 1), repeat=3))
        if level < len(enc.dense):  # every vertex its own entry: exactly one at each position of the volume
            assert (n + 1) ** 3 <= enc.table_size
            continue
        rows = set()
        for vertex in vertices:
            row = 0
            for v, prime in zip(vertex, HASH_PRIMES, strict=True):
                row ^= v * prime
            rows.add(row % enc.table_size)
        assert len(vertices) > enc.table_size and len(rows) <= enc.table_size  # more vertices than entries
    # a dense level's entry changes the encoding at its own vertex only
    with torch.no_grad():
        volume = enc.dense[1]
        volume.zero_()
        volume[0, :, 2, 5, 1] = torch.tensor([1.0, -2.0])
        lo, hi = torch.tensor(BOX)
        vertices = torch.tensor(list(itertools.product(range(7), repeat=3)), dtype=torch.float32)
        features = enc(lo + vertices / 6 * (hi - lo))[:, 2:4]  # level 1's features at every vertex
    hit = (vertices == torch.tensor([2.0, 5.0, 1.0])).all(-1)
    torch.testing.assert_close(features[hit], torch.tensor([[1.0, -2.0]]))
    assert features[~hit].abs().max() < 1e-6


@pytest.mark.parametrize("points_need_grad", [False, True])  # the tables' fast path; autograd's, as for normals
def test_gradcheck_in_float64(points_need_grad):
    enc = small_encoding(log2_table_size=8, n_levels=3, finest=12).double()  # levels dense and hashed
    lo, hi = torch.tensor(BOX, dtype=torch.float64)
    points = lo + torch.rand(6, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * (hi - lo)
    points.requires_grad_(points_need_grad)
    parameters = [enc.hashed] + list(enc.dense)

    # the tables enter as arguments (functional_call), so that gradcheck perturbs them too
    def functional(x, *tables):
        return torch.func.functional_call(enc, {"hashed": tables[0], **{f"dense.{i}": t for i, t in
                                                                         enumerate(tables[1:])}}, (x,))

    tables = [p.detach().clone().requires_grad_(True) for p in parameters]
    assert torch.autograd.gradcheck(functional, (points, *tables), eps=1e-6, atol=1e-8, rtol=1e-6)


def test_points_outside_the_box_take_the_features_of_the_nearest_point_on_it():
    enc = small_encoding()
    lo, hi = torch.tensor(BOX)
    outside = torch.tensor([[-3.0, 0.0, 1.0], [0.5, 9.0, -4.0]])
    nearest = torch.maximum(torch.minimum(outside, hi), lo)
    torch.testing.assert_close(enc(outside), enc(nearest))


def test_needs_bounds_and_rejects_bad_settings():
    with pytest.raises(RuntimeError, match="HashGridEncoding has no bounds"):
        HashGridEncoding(n_levels=2, log2_table_size=8, finest=32)(torch.zeros(1, 3))
    with pytest.raises(ValueError, match=r"encoding.position.finest: .* got finest=8"):
        HashGridEncoding(coarsest=16, finest=8)
    with pytest.raises(ValueError, match=r"encoding.position.log2_table_size: .* got log2_table_size=0"):
        HashGridEncoding(log2_table_size=0)


def test_coarse_and_fine_fields_get_tables_of_their_own():
    enc = small_encoding()
    head = functools.partial(MLPViewDependence, direction_encoding=PositionalEncoding(4), hidden=16)
    field = functools.partial(NeRFField, enc, head, depth=1, width=16, skips=())
    coarse, fine = field(), field()
    assert coarse.position_encoding.hashed is not fine.position_encoding.hashed
    assert not set(map(id, coarse.parameters())) & set(map(id, fine.parameters()))


def test_the_box_travels_with_the_weights():
    # what nerfexp-eval and resume rely on: a field loaded from a trained one's state has its box
    def field():
        return NeRFField(HashGridEncoding(n_levels=2, log2_table_size=8, coarsest=2, finest=8),
                         functools.partial(MLPViewDependence, direction_encoding=PositionalEncoding(4), hidden=8),
                         depth=1, width=8, skips=())

    trained, loaded = field(), field()
    trained.position_encoding.set_bounds(torch.tensor(BOX))
    assert not loaded.position_encoding.has_bounds
    loaded.load_state_dict(trained.state_dict())
    assert loaded.position_encoding.has_bounds
    x = torch.rand(5, 3)
    torch.testing.assert_close(loaded.density(x), trained.density(x))


def test_under_bf16_autocast_the_lookups_stay_in_float32():
    # the table's features are read and interpolated in its own precision: the same numbers as without autocast
    enc = small_encoding(log2_table_size=8)
    points = torch.rand(64, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1
    expected = enc(points)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        features = enc(points)
    assert features.dtype == torch.float32
    torch.testing.assert_close(features, expected, atol=0, rtol=0)


def rows_read(enc: HashGridEncoding, points: torch.Tensor) -> set[tuple[int, int]]:
    """The (hashed level, row) entries the encoding of points [N, 3] reads: every corner of every hashed level."""
    lo, hi = torch.tensor(BOX, dtype=torch.float64)
    read = set()
    for p in points.double():
        unit = ((p - lo) / (hi - lo)).clamp(0, 1).tolist()
        for level, n in enumerate(enc.resolutions[len(enc.dense):], start=len(enc.dense)):
            cell = [min(math.floor(u * n), n - 1) for u in unit]
            for corner in itertools.product((0, 1), repeat=3):
                read.add(hashed_row(enc, level, [c + o for c, o in zip(cell, corner, strict=True)]))
    return read


# 2 hashed levels of 1024 rows; 8 rows read per point and level: 40 points read fewer rows than the table
# has (summed by sorting them), 400 more (summed over the whole table, the rows read picked out)
@pytest.mark.parametrize("n_points", [40, 400])
def test_sparse_gradients_hold_each_row_read_once_with_the_dense_gradients_sum(n_points, device):
    dense, sparse = small_encoding(), small_encoding(sparse_gradients=True)  # the same tables (seeded)
    dense, sparse = dense.to(device), sparse.to(device)
    assert sparse.state_dict().keys() == dense.state_dict().keys()  # checkpoints of either load in the other
    generator = torch.Generator().manual_seed(2)
    lo, hi = torch.tensor(BOX)
    points = (lo + torch.rand(n_points, 3, generator=generator) * (hi - lo)).to(device)
    weights = torch.randn(dense.out_dim, generator=generator).to(device)
    for enc in (dense, sparse):
        (enc(points) @ weights).sum().backward()
    grad = sparse.hashed.grad
    assert grad.is_sparse and (grad.sparse_dim(), grad.dense_dim()) == (2, 1) and grad.shape == sparse.hashed.shape
    rows = [tuple(index) for index in grad._indices().T.tolist()]
    assert rows == sorted(set(rows))  # summed: each row once, in order
    assert set(rows) == rows_read(sparse, points.cpu()) and len(rows) < sparse.hashed[..., 0].numel()
    torch.testing.assert_close(grad.to_dense(), dense.hashed.grad)  # the dense gradient, up to summation order
    for a, b in zip(dense.dense, sparse.dense, strict=True):  # the dense levels keep dense gradients
        assert not b.grad.is_sparse  # (the fused kernel's, where it was built, sum in another order)
        torch.testing.assert_close(a.grad, b.grad)


def test_flat_entry_indices_widen_to_int64_where_int32_would_overflow():
    rows = torch.tensor([0, 5, 2**31 - 1], dtype=torch.int32)  # the last row of a table of 2^31 rows
    small = flat_indices(rows[:2], n_rows=6, n_features=2)
    assert small.dtype == torch.int32 and small.tolist() == [[0, 10], [1, 11]]  # r F + f, feature-first
    large = flat_indices(rows, n_rows=2**31, n_features=2)
    assert large.dtype == torch.int64 and large[:, -1].tolist() == [2**32 - 2, 2**32 - 1]
