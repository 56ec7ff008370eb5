"""The hash encoding's fused CPU kernel (src/nerfexp/kernels/hash_encoding.cpp) against independent truth and the
torch path it replaces: features against the float64 reference written from the paper's definition, table
gradients against the torch path's (NERFEXP_KERNELS=off) to float32 rounding, with hash collisions, positions on
cell faces and the box's edges and outside it, empty and one-element batches, non-contiguous inputs and
gradients, bf16 autocast around it; and the fallback where no compiler builds it."""

import copy
import json
import re
import subprocess
import sys

import pytest
import torch

from nerfexp import kernels
from nerfexp.nerf import hashgrid
from tests.nerf.hashgrid_reference import BOX, reference_features, small_encoding

FUSED = kernels.kernel("hash_encoding")
needs_kernel = pytest.mark.skipif(FUSED is None, reason="the hash encoding's kernel was not built (no C++ compiler)")


def edge_points(enc, n_random: int = 300) -> torch.Tensor:
    """Positions [M, 3] (float32) inside the box, on cell faces of every level (unit u with u N an integer),
    at the box's corners and centre, on its faces, and outside it."""
    generator = torch.Generator().manual_seed(3)
    lo, hi = torch.tensor(BOX)
    unit = [torch.rand(n_random, 3, generator=generator)]
    for n in enc.resolutions:  # a vertex of each level, on three faces at once
        unit.append(torch.randint(0, n + 1, (8, 3), generator=generator) / n)
    unit.append(torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.5, 0.5, 0.5], [1.0, 0.3, 0.0], [0.0, 1.0, 0.7],
                              [1.5, 0.5, 0.5], [-0.2, 0.3, 1.0], [2.0, -1.0, 3.0]]))
    return lo + torch.cat(unit) * (hi - lo)


def features_and_grads(enc, points: torch.Tensor, probe: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
    for p in enc.parameters():
        p.grad = None
    out = enc(points)
    out.backward(probe)
    return out.detach(), [torch.zeros_like(p) if p.grad is None else p.grad.clone() for p in enc.parameters()]


@needs_kernel
@pytest.mark.parametrize("log2_table_size", [10, 4, 20])  # mixed; every level hashed (collisions); every level dense
def test_the_kernel_matches_the_float64_reference_and_the_torch_paths_gradients(log2_table_size, monkeypatch):
    enc = small_encoding(log2_table_size=log2_table_size)
    points = edge_points(enc)
    probe = torch.randn(len(points), enc.out_dim, generator=torch.Generator().manual_seed(4))
    assert enc._fused_kernel(points) is FUSED  # float32 on a CPU, positions not differentiated: the kernel runs
    fused, fused_grads = features_and_grads(enc, points, probe)
    torch.testing.assert_close(fused.double(), reference_features(enc, points), atol=2e-6, rtol=0)
    monkeypatch.setenv(kernels.SWITCH, "off")
    assert enc._fused_kernel(points) is None
    torch_path, torch_grads = features_and_grads(enc, points, probe)
    torch.testing.assert_close(fused, torch_path, atol=2e-6, rtol=0)
    for mine, theirs in zip(fused_grads, torch_grads, strict=True):
        torch.testing.assert_close(mine, theirs, atol=1e-5, rtol=1e-5)  # sums in another order


@needs_kernel
def test_colliding_vertices_share_their_entry_and_its_gradient_sums_theirs():
    # Every level hashed into 2 rows: almost every corner collides; an entry's gradient is the sum of the weights
    # times the incoming gradient of every corner read from it, over every point.
    enc = small_encoding(log2_table_size=1, features_per_level=1)
    points = edge_points(enc)
    out, grads = features_and_grads(enc, points, torch.ones(len(points), enc.out_dim))
    # with an incoming gradient of 1, each level's entries sum the points' trilinear weights: 1 per point
    assert torch.allclose(grads[-1].sum((1, 2)), torch.full((enc.hashed.shape[0],), float(len(points))))
    torch.testing.assert_close(out.double(), reference_features(enc, points), atol=2e-6, rtol=0)


@needs_kernel
@pytest.mark.parametrize("n", [0, 1])
def test_empty_and_one_element_batches(n):
    enc = small_encoding()
    points = edge_points(enc)[:n]
    out, grads = features_and_grads(enc, points, torch.ones(n, enc.out_dim))
    assert out.shape == (n, enc.out_dim)
    if n:
        torch.testing.assert_close(out.double(), reference_features(enc, points), atol=2e-6, rtol=0)
    assert all((g.abs().sum() > 0) == (n > 0) for g in grads)


@needs_kernel
def test_non_contiguous_positions_and_gradients_give_the_contiguous_ones_results():
    enc = small_encoding()
    points = edge_points(enc)
    probe = torch.randn(len(points), enc.out_dim, generator=torch.Generator().manual_seed(5))
    strided_points = torch.stack([points, -points], 1)[:, 0]  # [M, 3], every other row of a larger tensor
    strided_probe = probe.T.contiguous().T  # [M, L F], column-major
    assert not strided_points.is_contiguous() and not strided_probe.is_contiguous()
    out, grads = features_and_grads(enc, points, probe)
    strided_out, strided_grads = features_and_grads(enc, strided_points, strided_probe)
    assert torch.equal(out, strided_out) and all(torch.equal(a, b) for a, b in zip(grads, strided_grads, strict=True))


@needs_kernel
def test_under_bf16_autocast_the_kernel_reads_float32_positions_and_writes_float32_features():
    enc = small_encoding()
    points = edge_points(enc)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = enc(points)
    assert out.dtype == torch.float32 and torch.equal(out, enc(points))


def test_positions_that_need_a_gradient_take_the_torch_path():
    enc = small_encoding()
    points = edge_points(enc).requires_grad_()
    assert enc._fused_kernel(points) is None  # autograd's own gather: differentiable in positions, and twice
    assert enc._fused_kernel(points.detach()) is FUSED  # the kernel where it was built


def test_on_any_device_but_the_cpu_the_torch_path_runs(monkeypatch):
    # a GPU's tensors never reach the CPU kernel: the meta device (in every torch build) stands for a GPU here,
    # and a stand-in for the kernel is "built", so that the choice is seen whether or not a compiler is here
    built = object()
    monkeypatch.setattr(hashgrid, "kernel", lambda name: built)
    enc = small_encoding()
    assert enc._fused_kernel(torch.rand(5, 3)) is built  # float32 on the CPU: the kernel
    assert enc.to("meta")._fused_kernel(torch.rand(5, 3, device="meta")) is None  # elsewhere: the torch path


@needs_kernel
def test_the_kernel_refuses_tensors_off_the_cpu_or_of_another_shape_in_one_line():
    enc = small_encoding()
    volumes = [volume[0] for volume in enc.dense]
    shape = enc.kernel_shape()
    with pytest.raises(RuntimeError, match="hash_encoding: unit is on meta, not the CPU"):
        FUSED.forward(torch.rand(5, 3, device="meta"), volumes, enc.hashed.detach(), *shape)
    with pytest.raises(RuntimeError, match=r"hash_encoding: unit must be \[N, 3\], got \[5, 2\]"):
        FUSED.forward(torch.rand(5, 2), volumes, enc.hashed.detach(), *shape)
    with pytest.raises(RuntimeError, match="hash_encoding: hashed is not contiguous"):
        FUSED.forward(torch.rand(5, 3), volumes, enc.hashed.detach().transpose(0, 1), *shape)
    with pytest.raises(RuntimeError, match=r"hash_encoding: grad must be \[5, 8\], got \[5, 7\]"):
        FUSED.backward(torch.rand(5, 3), torch.rand(5, 7), volumes, enc.hashed.detach(), *shape)


@needs_kernel
def test_the_kernel_refuses_other_dtypes_and_sizes_that_would_index_outside_its_tables_in_one_line():
    enc = small_encoding()
    volumes, hashed = [volume[0].detach() for volume in enc.dense], enc.hashed.detach()
    (dense_res, hashed_res, features), unit = enc.kernel_shape(), torch.rand(5, 3)
    grad = torch.rand(5, enc.out_dim)
    assert dense_res and hashed_res and hashed.shape[1] > 1  # both kinds of level, each checked
    refused = [  # (the call's arguments after the positions, the message)
        ((volumes, hashed.double(), dense_res, hashed_res, features), "hash_encoding: hashed is Double, not float32"),
        (([volumes[0].half(), *volumes[1:]], hashed, dense_res, hashed_res, features),
         "hash_encoding: a dense volume is Half, not float32"),
        ((volumes, hashed, dense_res, hashed_res, 0), "hash_encoding: features per level must be >= 1, got 0"),
        ((volumes, hashed[:, :-1].contiguous(), dense_res, hashed_res, features),
         f"hash_encoding: the hashed table's T = {hashed.shape[1] - 1} rows must be a power of two in [1, 2^32]"),
        ((volumes, hashed, dense_res, [0, *hashed_res[1:]], features),
         "hash_encoding: hashed level 0 has 0 cells per side: expected 1 to 2^24"),
        ((volumes, hashed, dense_res, [*hashed_res[:-1], 2 ** 24 + 1], features),
         f"hash_encoding: hashed level {len(hashed_res) - 1} has {2 ** 24 + 1} cells per side: expected 1 to 2^24"),
        ((volumes, hashed, [0, *dense_res[1:]], hashed_res, features),
         "hash_encoding: dense level 0 has 0 cells per side: expected 1 to 1624"),
        ((volumes, hashed, [2 ** 40, *dense_res[1:]], hashed_res, features),  # (n+1)^3 past int64 and uint32
         f"hash_encoding: dense level 0 has {2 ** 40} cells per side: expected 1 to 1624"),
        ((volumes, hashed, [dense_res[0] + 1, *dense_res[1:]], hashed_res, features),  # more cells than stored
         f"hash_encoding: dense level 0 must be [{features}, {dense_res[0] + 2}, "),
        ((volumes[::-1], hashed, dense_res, hashed_res, features), "hash_encoding: dense level 0 must be ["),
    ]
    for arguments, message in refused:  # each message as written (re.escape: no pattern)
        with pytest.raises(RuntimeError, match=re.escape(message)):
            FUSED.forward(unit, *arguments)
        with pytest.raises(RuntimeError, match=re.escape(message)):
            FUSED.backward_rows(unit, grad, *arguments)
    with pytest.raises(RuntimeError, match="hash_encoding: unit is Double, not float32"):
        FUSED.forward(unit.double(), volumes, hashed, dense_res, hashed_res, features)
    with pytest.raises(RuntimeError, match="hash_encoding: grad is Double, not float32"):
        FUSED.backward(unit, grad.double(), volumes, hashed, dense_res, hashed_res, features)
    sums = [torch.zeros_like(volume) for volume in volumes]
    with pytest.raises(RuntimeError, match="hash_encoding: hashed is Long, not float32"):
        FUSED.backward_into(unit, grad, sums, torch.zeros_like(hashed, dtype=torch.long), dense_res, hashed_res,
                            features)
    assert not any(s.any() for s in sums)  # nothing was written


HIDDEN_COMPILER = """
import json, logging, sys, torch
logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(name)s: %(message)s")
from tests.nerf.hashgrid_reference import small_encoding
enc = small_encoding()
points = torch.rand(50, 3)
print(json.dumps({"kernel": enc._fused_kernel(points) is not None, "features": enc(points).tolist()}))
"""


def test_without_a_compiler_the_torch_path_runs_after_one_line(tmp_path, monkeypatch):
    # a machine without a C++ compiler: the build fails at first use; the encoding runs the torch path
    env = {"CXX": str(tmp_path / "no-compiler"), "CC": str(tmp_path / "no-compiler"),
           "TORCH_EXTENSIONS_DIR": str(tmp_path / "cache"), "PATH": "/usr/bin:/bin"}
    result = subprocess.run([sys.executable, "-c", HIDDEN_COMPILER], capture_output=True, text=True, timeout=300,
                            env={**subprocess.os.environ, **env})
    assert result.returncode == 0, result.stderr[-3000:]
    said = [line for line in result.stderr.splitlines() if line.startswith("nerfexp.kernels:")]
    assert len(said) == 1 and "kernel hash_encoding not built" in said[0] and "torch path runs instead" in said[0]
    record = json.loads(result.stdout)
    assert record["kernel"] is False
    monkeypatch.setenv(kernels.SWITCH, "off")
    torch.manual_seed(0)
    enc = small_encoding()
    assert torch.allclose(torch.tensor(record["features"]), enc(torch.rand(50, 3)))


@needs_kernel
def test_with_sparse_gradients_the_kernel_gives_the_torch_paths_rows_read(monkeypatch):
    # sparse_gradients: the hashed table's gradient holds the rows the batch read, each once and in order, as
    # the torch path's; the dense levels' gradients stay dense
    enc = small_encoding(sparse_gradients=True)  # hashed levels of 1,024 rows, 50 points read 400 corners each
    points = edge_points(enc)[:50]
    probe = torch.randn(len(points), enc.out_dim, generator=torch.Generator().manual_seed(6))
    grads = []
    for switch in ("on", "off"):
        monkeypatch.setenv(kernels.SWITCH, switch)
        assert (enc._fused_kernel(points) is FUSED) == (switch == "on")
        grads.append(features_and_grads(enc, points, probe)[1])
    (fused, *fused_dense), (reference, *torch_dense) = grads  # the hashed table first, then the dense volumes
    assert fused.is_sparse and reference.is_sparse
    rows = fused._indices()[0] * enc.table_size + fused._indices()[1]
    assert (rows[1:] > rows[:-1]).all()  # each row once, in order (autograd's accumulation drops the flag only)
    reference = reference.coalesce()
    assert 0 < fused._nnz() < enc.hashed[..., 0].numel()  # some rows read, not all
    assert torch.equal(fused._indices(), reference.indices())
    torch.testing.assert_close(fused._values(), reference.values(), atol=1e-5, rtol=1e-5)
    for mine, theirs in zip(fused_dense, torch_dense, strict=True):
        torch.testing.assert_close(mine, theirs, atol=1e-5, rtol=1e-5)


def segments_loss(encodings_and_points, probes) -> torch.Tensor:
    """One loss over several calls of the encodings (as the renderer's segments and networks call them)."""
    return sum((enc(points) * probe).sum() for (enc, points), probe in zip(encodings_and_points, probes, strict=True))


@needs_kernel
def test_the_calls_of_one_backward_pass_sum_into_one_gradient_equal_to_the_torch_paths(monkeypatch):
    # the renderer calls each network's encoding once per segment: the fused kernel sums every call's gradient into
    # the tensors the pass's first call handed autograd; the sum equals the torch path's (autograd's sum of a
    # dense gradient per call) to float32 rounding, for the hashed table and every dense volume, for two copies
    # of the encoding (the coarse and the fine network's) in one loss
    enc = small_encoding(log2_table_size=10)
    other = copy.deepcopy(enc)
    points = edge_points(enc)
    calls = [(enc, points[:40]), (other, points[40:90]), (enc, points[90:]), (enc, points[:7]), (other, points[3:])]
    generator = torch.Generator().manual_seed(7)
    probes = [torch.randn(len(p), enc.out_dim, generator=generator) for _, p in calls]
    grads = {}
    for switch in ("on", "off"):
        monkeypatch.setenv(kernels.SWITCH, switch)
        for p in [*enc.parameters(), *other.parameters()]:
            p.grad = None
        segments_loss(calls, probes).backward()
        grads[switch] = [p.grad.clone() for p in [*enc.parameters(), *other.parameters()]]
    for mine, theirs in zip(grads["on"], grads["off"], strict=True):
        torch.testing.assert_close(mine, theirs, atol=1e-5, rtol=1e-5)


@needs_kernel
def test_backward_passes_accumulate_as_autograd_does_and_autograd_keeps_the_summed_tensor(monkeypatch):
    # each pass starts its own sums; a second pass (retain_graph) adds to the gradient as autograd always does, and
    # the gradient autograd stores is the tensor the calls summed into (no copy), made once per pass
    enc = small_encoding(log2_table_size=10)
    made = []  # per call: (whether it made the pass's tensors, the hashed table's tensor's storage)
    sums_of = enc.pass_gradients.of

    def recorded(tables):
        sums, new = sums_of(tables)
        made.append((new, sums[0].data_ptr()))
        return sums, new
    monkeypatch.setattr(enc.pass_gradients, "of", recorded)
    points = edge_points(enc)
    calls = [(enc, points[:100]), (enc, points[100:])]
    probes = [torch.ones(len(p), enc.out_dim) for _, p in calls]
    loss = segments_loss(calls, probes)
    loss.backward(retain_graph=True)
    once = [p.grad.clone() for p in enc.parameters()]
    assert [new for new, _ in made] == [True, False] and enc.hashed.grad.data_ptr() == made[0][1]
    loss.backward()
    assert [new for new, _ in made] == [True, False, True, False]
    for twice, single in zip((p.grad for p in enc.parameters()), once, strict=True):
        torch.testing.assert_close(twice, 2 * single)
    # the whole batch in one call: the same gradient as the two calls' sum
    for p in enc.parameters():
        p.grad = None
    enc(points).sum().backward()
    for whole, single in zip((p.grad for p in enc.parameters()), once, strict=True):
        torch.testing.assert_close(whole, single, atol=1e-5, rtol=1e-5)


@needs_kernel
def test_passes_of_autograd_grad_are_told_apart_while_an_earlier_ones_gradients_are_held(monkeypatch):
    # torch.autograd.grad stores no gradient: the tensors a pass summed into are handed back and held here, alive,
    # while the next pass runs; each pass still starts its own (the tables' hooks end a pass whether autograd
    # stores or returns the gradient), and both equal the torch path's
    enc = small_encoding(log2_table_size=10)
    made = []
    sums_of = enc.pass_gradients.of

    def recorded(tables):
        sums, new = sums_of(tables)
        made.append(new)
        return sums, new
    monkeypatch.setattr(enc.pass_gradients, "of", recorded)
    points = edge_points(enc)
    calls = [(enc, points[:100]), (enc, points[100:200]), (enc, points[200:])]
    generator = torch.Generator().manual_seed(9)
    probes = [torch.randn(len(p), enc.out_dim, generator=generator) for _, p in calls]
    first = torch.autograd.grad(segments_loss(calls, probes), list(enc.parameters()))
    second = torch.autograd.grad(segments_loss(calls, [2 * probe for probe in probes]), list(enc.parameters()))
    assert made == [True, False, False, True, False, False]
    assert all(p.grad is None for p in enc.parameters())
    monkeypatch.setenv(kernels.SWITCH, "off")
    reference = torch.autograd.grad(segments_loss(calls, probes), list(enc.parameters()))
    for mine, twice, theirs in zip(first, second, reference, strict=True):
        torch.testing.assert_close(mine, theirs, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(twice, 2 * theirs, atol=2e-5, rtol=1e-5)


@needs_kernel
def test_summing_into_gradients_of_another_shape_is_a_one_line_error():
    enc = small_encoding()
    volumes = [torch.zeros_like(volume[0]) for volume in enc.dense]
    with pytest.raises(RuntimeError, match=r"hash_encoding: hashed must be \["):
        FUSED.backward_into(torch.rand(5, 3), torch.rand(5, enc.out_dim), volumes, torch.zeros(1, 4, 2),
                            *enc.kernel_shape())


@needs_kernel
def test_the_kernel_clamps_positions_outside_the_unit_box_never_reading_outside_its_tables():
    # the encoding clamps before it calls the kernel; the kernel clamps again, so that a wrong call (a position
    # outside [0, 1], a NaN) reads its tables' edges, not memory beyond them: NaN as 0
    enc = small_encoding()
    volumes = [volume[0] for volume in enc.dense]
    outside = torch.tensor([[-0.5, 1.5, 0.25], [3.0, -2.0, 1.0], [float("nan"), 0.5, 1.0]])
    inside = torch.tensor([[0.0, 1.0, 0.25], [1.0, 0.0, 1.0], [0.0, 0.5, 1.0]])
    features = FUSED.forward(outside, volumes, enc.hashed.detach(), *enc.kernel_shape())
    assert torch.equal(features, FUSED.forward(inside, volumes, enc.hashed.detach(), *enc.kernel_shape()))


@needs_kernel
def test_a_pass_mixing_the_kernel_and_the_torch_path_sums_every_calls_gradient(monkeypatch):
    # positions that need a gradient take the torch path: its dense gradient meets the kernel's in autograd's sum,
    # whichever comes first; every call's gradient reaches the table (the torch path throughout as the reference)
    enc = small_encoding(log2_table_size=10)
    points = edge_points(enc)
    generator = torch.Generator().manual_seed(8)
    probes = [torch.randn(n, enc.out_dim, generator=generator) for n in (60, 80, 50, 70)]
    parts = [points[:60], points[60:140].clone().requires_grad_(), points[140:190], points[190:260]]

    def gradients() -> list[torch.Tensor]:
        for p in enc.parameters():
            p.grad = None
        sum((enc(x) * probe).sum() for x, probe in zip(parts, probes, strict=True)).backward()
        return [p.grad.clone() for p in enc.parameters()]
    mixed = gradients()
    monkeypatch.setenv(kernels.SWITCH, "off")
    for mine, theirs in zip(mixed, gradients(), strict=True):
        torch.testing.assert_close(mine, theirs, atol=1e-5, rtol=1e-5)


@needs_kernel
def test_with_a_frozen_table_the_others_get_the_torch_paths_gradients(monkeypatch):
    # the hashed table frozen (no gradient): each call's own gradients, no shared sums; the dense volumes' equal
    # the torch path's and the frozen table gets none
    enc = small_encoding(log2_table_size=10)
    enc.hashed.requires_grad_(False)
    points = edge_points(enc)
    grads = {}
    for switch in ("on", "off"):
        monkeypatch.setenv(kernels.SWITCH, switch)
        for p in enc.dense:
            p.grad = None
        (enc(points[:100]).square().sum() + enc(points[100:]).sum()).backward()
        grads[switch] = [p.grad.clone() for p in enc.dense]
        assert enc.hashed.grad is None
    for mine, theirs in zip(grads["on"], grads["off"], strict=True):
        torch.testing.assert_close(mine, theirs, atol=1e-5, rtol=1e-5)
