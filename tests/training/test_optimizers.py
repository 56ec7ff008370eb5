"""LazyAdam against independent truth: torch.optim.Adam on dense gradients (bit for bit), a float64 reference
of the lazy rule written one row at a time, and dense Adam where every row is touched every step; its fused CPU
kernel (lazy_adam.cpp, float32) against the same reference and the torch path, to float32 rounding."""

import math

import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.utils import get_class

from nerfexp import kernels
from nerfexp.errors import ConfigError
from nerfexp.training import optimizers
from nerfexp.training.optimizers import LazyAdam, flat_rows, fused_kernel, summed_rows

SETTINGS = dict(lr=0.05, betas=(0.8, 0.95), eps=1e-6)
FUSED = kernels.kernel("lazy_adam")
needs_kernel = pytest.mark.skipif(FUSED is None, reason="the lazy Adam kernel was not built (no C++ compiler)")


def sparse(indices: list[list[int]], values: torch.Tensor, shape) -> torch.Tensor:
    """A COO gradient of ``shape`` from indices [S, nnz] and values [nnz, *D], not coalesced."""
    return torch.sparse_coo_tensor(torch.tensor(indices), values, shape, check_invariants=True)


def test_flat_rows_count_row_major():
    indices = torch.tensor([[0, 1, 2, 2], [0, 3, 1, 4]])  # rows of a [3, 5] grid
    assert flat_rows(indices, torch.Size([3, 5])).tolist() == [0, 8, 11, 14]
    assert flat_rows(torch.tensor([[4, 2]]), torch.Size([7])).tolist() == [4, 2]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("options", [dict(), dict(weight_decay=0.1), dict(amsgrad=True), dict(maximize=True),
                                     dict(weight_decay=0.01, decoupled_weight_decay=True),
                                     dict(fused=True), dict(fused=True, weight_decay=0.1)])
def test_dense_gradients_get_torch_adams_update_bit_for_bit(options, dtype):
    generator = torch.Generator().manual_seed(0)
    start = [torch.randn(4, 3, generator=generator, dtype=dtype), torch.randn(5, generator=generator, dtype=dtype),
             torch.randn(2, 3, 2, generator=generator, dtype=dtype)]
    runs = []
    for optimizer_class in (torch.optim.Adam, LazyAdam):
        params = [torch.nn.Parameter(p.clone()) for p in start]
        groups = [{"params": params[:2]}, {"params": params[2:], "lr": 0.2, "weight_decay": 0.0}]
        optimizer = optimizer_class(groups, **SETTINGS, **options)
        grads = torch.Generator().manual_seed(1)
        for step in range(6):
            for i, p in enumerate(params):  # parameter 1 has no gradient on odd steps: Adam skips it
                p.grad = None if (i == 1 and step % 2) else torch.randn(p.shape, generator=grads, dtype=dtype)
            optimizer.step()
        runs.append((params, optimizer.state_dict()))
    (adam_params, adam_state), (lazy_params, lazy_state) = runs
    assert all(torch.equal(a, b) for a, b in zip(adam_params, lazy_params, strict=True))
    assert adam_state["state"].keys() == lazy_state["state"].keys()
    for key, state in adam_state["state"].items():
        assert state.keys() == lazy_state["state"][key].keys()
        assert all(torch.equal(value, lazy_state["state"][key][name]) for name, value in state.items())
    assert lazy_state["state"][1]["step"] == 3  # counted on the steps it had a gradient


def reference_lazy_adam(start: torch.Tensor, gradients: list[list[tuple[tuple[int, ...], list[float]]] | None],
                        lr: float, betas: tuple[float, float], eps: float) -> tuple[torch.Tensor, dict]:
    """The lazy rule one row at a time, in float64 Python numbers. ``gradients``: per step, None (no
    gradient) or a list of (row index, row gradient [F]) pairs, a row possibly repeated (its gradients
    add). Returns the parameter and {row: (m, v)} of every row ever touched."""
    param = {row: list(map(float, start[row].tolist())) for row in _all_rows(start.shape[:-1])}
    moments = {}
    step = 0
    beta1, beta2 = betas
    for gradient in gradients:
        if gradient is None:
            continue
        step += 1
        summed = {}
        for row, values in gradient:
            summed[row] = [a + b for a, b in zip(summed.get(row, [0.0] * len(values)), values, strict=True)]
        for row, g in summed.items():
            m, v = moments.get(row, ([0.0] * len(g), [0.0] * len(g)))
            m = [beta1 * mi + (1 - beta1) * gi for mi, gi in zip(m, g, strict=True)]
            v = [beta2 * vi + (1 - beta2) * gi * gi for vi, gi in zip(v, g, strict=True)]
            moments[row] = (m, v)
            m_hat = [mi / (1 - beta1**step) for mi in m]
            v_hat = [vi / (1 - beta2**step) for vi in v]
            param[row] = [p - lr * mh / (math.sqrt(vh) + eps) for p, mh, vh in zip(param[row], m_hat, v_hat,
                                                                                     strict=True)]
    out = torch.tensor([param[row] for row in _all_rows(start.shape[:-1])], dtype=torch.float64)
    return out.view(start.shape), moments


def _all_rows(shape) -> list[tuple[int, ...]]:
    return [tuple(index) for index in torch.cartesian_prod(*[torch.arange(n) for n in shape]).view(-1, len(shape))
            .tolist()]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_lazy_update_matches_a_float64_reference_row_by_row(dtype, device):
    # a [2, 4, 3] table (2 sparse dims: level and row, 3 features); steps touch few rows, some twice in one
    # gradient, one step none at all (no gradient: the step count stays). float64: the torch path, to 1e-12;
    # float32: the fused kernel on a CPU (the torch path on a GPU), to float32 rounding
    if dtype == torch.float32 and device.type == "cpu" and FUSED is None:
        pytest.skip("the lazy Adam kernel was not built (no C++ compiler)")
    shape = (2, 4, 3)
    start = torch.randn(shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    tolerance = 1e-12 if dtype == torch.float64 else 2e-6
    generator = torch.Generator().manual_seed(1)
    touched = [[(0, 1), (1, 3), (0, 1)], [(1, 0)], None, [(0, 1), (1, 0), (1, 2), (1, 2), (1, 2)], [(0, 3)]]
    gradients = [None if rows is None else [(row, torch.randn(3, generator=generator, dtype=torch.float64).tolist())
                                            for row in rows] for rows in touched]
    expected, moments = reference_lazy_adam(start, gradients, **SETTINGS)

    param = torch.nn.Parameter(start.to(device, dtype))
    assert fused_kernel(param, param.detach()) is (FUSED if dtype == torch.float32 and device.type == "cpu" else None)
    optimizer = LazyAdam([param], **SETTINGS)
    for gradient in gradients:
        param.grad = None if gradient is None else sparse(
            [[row[0] for row, _ in gradient], [row[1] for row, _ in gradient]],
            torch.tensor([values for _, values in gradient], dtype=dtype), shape).to(device)
        optimizer.step()
    state = {key: value.cpu() for key, value in optimizer.state[param].items()}
    assert state["step"] == 4
    param = param.detach().cpu()
    torch.testing.assert_close(param.double(), expected, rtol=tolerance, atol=tolerance)
    never = [row for row in _all_rows(shape[:2]) if row not in moments]
    assert never == [(0, 0), (0, 2), (1, 1)]
    for row in never:  # never touched: not moved, moments still zero
        assert torch.equal(param[row], start[row].to(dtype)) and not state["exp_avg"][row].any()
    for row, (m, v) in moments.items():
        torch.testing.assert_close(state["exp_avg"][row].double(), torch.tensor(m, dtype=torch.float64),
                                   rtol=tolerance, atol=0)
        torch.testing.assert_close(state["exp_avg_sq"][row].double(), torch.tensor(v, dtype=torch.float64),
                                   rtol=tolerance, atol=0)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_lazy_update_is_torch_adams_on_the_rows_touched_bit_for_bit(dtype, monkeypatch):
    # the torch path (kernels off) against an independent computation: each step, the rows a gradient touches
    # (summed where repeated) taken out as a parameter of their own with their moments and the table's step
    # count, and updated by torch.optim.Adam itself; every other row left as it is. Bit for bit in either dtype
    monkeypatch.setenv(kernels.SWITCH, "off")
    shape = (2, 5, 3)
    generator = torch.Generator().manual_seed(2)
    start = torch.randn(shape, generator=generator, dtype=dtype)
    table = torch.nn.Parameter(start.clone())
    optimizer = LazyAdam([table], **SETTINGS)
    expected, m, v = start.clone().view(10, 3), torch.zeros(10, 3, dtype=dtype), torch.zeros(10, 3, dtype=dtype)
    touched = [[(0, 1), (1, 4), (0, 1)], [(1, 0), (0, 1)], None, [(1, 4), (1, 2), (1, 2), (0, 0)], [(0, 3)]]
    step = 0
    for rows in touched:
        if rows is None:
            table.grad = None
            optimizer.step()
            continue
        values = torch.randn(len(rows), 3, generator=generator, dtype=dtype)
        table.grad = sparse([[r for r, _ in rows], [c for _, c in rows]], values, shape)
        optimizer.step()
        step += 1
        flat = torch.tensor([5 * r + c for r, c in rows])
        summed = torch.zeros(10, 3, dtype=dtype).index_add_(0, flat, values)
        held = flat.unique()  # ascending, each once
        part = torch.nn.Parameter(expected[held].clone())
        reference = torch.optim.Adam([part], **SETTINGS)
        reference.state[part].update(step=torch.tensor(float(step - 1)), exp_avg=m[held].clone(),
                                     exp_avg_sq=v[held].clone())
        part.grad = summed[held]
        reference.step()
        expected[held], m[held], v[held] = part.detach(), reference.state[part]["exp_avg"], \
            reference.state[part]["exp_avg_sq"]
    state = optimizer.state[table]
    assert state["step"] == step == 4
    assert torch.equal(table.detach().view(10, 3), expected)
    assert torch.equal(state["exp_avg"].view(10, 3), m) and torch.equal(state["exp_avg_sq"].view(10, 3), v)
    untouched = [1 * 5 + 1, 1 * 5 + 3, 0 * 5 + 2, 0 * 5 + 4]  # rows (1, 1), (1, 3), (0, 2), (0, 4): never read
    assert torch.equal(expected[untouched], start.view(10, 3)[untouched])


def test_a_step_with_a_closure_uses_its_gradients_and_leaves_the_gradients_in_place(monkeypatch):
    # as Lightning steps: the closure computes the loss and the gradients (a sparse one from an embedding's
    # lookup, a dense one) inside step, which returns the loss; after it each parameter holds the gradient it
    # was updated by, sparse included (set aside during Adam's dense step only)
    monkeypatch.setenv(kernels.SWITCH, "off")
    generator = torch.Generator().manual_seed(3)
    table_start, weight_start = torch.randn(6, 2, generator=generator), torch.randn(2, generator=generator)
    rows = torch.tensor([4, 1, 4])
    runs = []
    for closure_step in (True, False):
        table, weight = torch.nn.Parameter(table_start.clone()), torch.nn.Parameter(weight_start.clone())
        optimizer = LazyAdam([table, weight], **SETTINGS)

        def closure():
            optimizer.zero_grad()
            loss = (torch.nn.functional.embedding(rows, table, sparse=True) @ weight).square().sum()
            loss.backward()
            return loss
        if closure_step:
            loss = optimizer.step(closure)
        else:
            loss = closure()
            assert optimizer.step() is None
        runs.append((loss.detach(), table.detach().clone(), weight.detach().clone(), table.grad, weight.grad))
    (loss, table, weight, table_grad, weight_grad), (loss_after, table_after, weight_after, *_) = runs
    assert torch.equal(loss, loss_after) and torch.equal(table, table_after) and torch.equal(weight, weight_after)
    assert table_grad.is_sparse and weight_grad is not None  # put back after the step
    assert torch.equal(table[[0, 2, 3, 5]], table_start[[0, 2, 3, 5]]) and not torch.equal(table[1], table_start[1])
    assert not torch.equal(weight, weight_start)


def test_on_any_device_but_the_cpu_the_torch_path_runs(monkeypatch):
    # a GPU's tensors never reach the CPU kernel: the meta device (in every torch build) stands for a GPU here,
    # and a stand-in for the kernel is "built", so that the choice is seen whether or not a compiler is here
    built = object()
    monkeypatch.setattr(optimizers, "kernel", lambda name: built)
    param = torch.zeros(4, 3)
    assert fused_kernel(param, param) is built  # contiguous float32 on the CPU: the kernel
    meta = torch.zeros(4, 3, device="meta")
    assert fused_kernel(meta, meta) is None  # elsewhere: the torch path


@needs_kernel
def test_the_kernel_refuses_tensors_off_the_cpu_or_of_another_shape_in_one_line():
    param, rows, values = torch.zeros(4, 3), torch.tensor([0, 2]), torch.ones(2, 3)
    moments = [torch.zeros(4, 3), torch.zeros(4, 3)]
    with pytest.raises(RuntimeError, match="lazy_adam: param is on meta, not the CPU"):
        FUSED.rows(param.to("meta"), *moments, rows, values, 1.0, 0.1, 0.9, 0.99, 1e-8)
    with pytest.raises(RuntimeError, match="lazy_adam: exp_avg is not contiguous"):
        FUSED.rows(param, torch.zeros(3, 4).T, moments[1], rows, values, 1.0, 0.1, 0.9, 0.99, 1e-8)
    with pytest.raises(RuntimeError, match=r"lazy_adam: rows \[U\] and values \[U, D\] of the parameter's D = 3"):
        FUSED.rows(param, *moments, rows, torch.ones(2, 4), 1.0, 0.1, 0.9, 0.99, 1e-8)
    assert not param.any()  # nothing was written


@needs_kernel
@pytest.mark.parametrize(("change", "message"), [
    ({"param": torch.zeros(4, 3, dtype=torch.float64)}, "lazy_adam: param is Double, not float32"),
    ({"values": torch.ones(2, 3, dtype=torch.bfloat16)}, "lazy_adam: values is BFloat16, not float32"),
    ({"rows": torch.tensor([0, 2], dtype=torch.int32)}, "lazy_adam: rows is Int, not int64"),
    ({"rows": torch.tensor([0, 4])}, r"lazy_adam: row 4 \(rows\[1\]\) is outside the parameter's 4 rows"),
    ({"rows": torch.tensor([-1, 2])}, r"lazy_adam: row -1 \(rows\[0\]\) is outside the parameter's 4 rows"),
    ({"rows": torch.tensor([2, 2])}, r"lazy_adam: rows must be ascending, each once: rows\[1\] = 2 follows 2"),
    ({"rows": torch.tensor([2, 0])}, r"lazy_adam: rows must be ascending, each once: rows\[1\] = 0 follows 2"),
    ({"step": 0.0}, "lazy_adam: expected step >= 1, lr >= 0, beta1 and beta2 in"),
    ({"beta2": 1.0}, "lazy_adam: expected step >= 1, lr >= 0, beta1 and beta2 in"),
    ({"eps": -1e-8}, "lazy_adam: expected step >= 1, lr >= 0, beta1 and beta2 in"),
])
def test_the_kernel_refuses_other_dtypes_rows_outside_or_out_of_order_and_bad_scalars_writing_nothing(change,
                                                                                                     message):
    call = {"param": torch.zeros(4, 3), "exp_avg": torch.zeros(4, 3), "exp_avg_sq": torch.zeros(4, 3),
            "rows": torch.tensor([0, 2]), "values": torch.ones(2, 3), "step": 1.0, "lr": 0.1, "beta1": 0.9,
            "beta2": 0.99, "eps": 1e-8} | change
    with pytest.raises(RuntimeError, match=message):
        FUSED.rows(*call.values())
    assert not any(call[key].any() for key in ("param", "exp_avg", "exp_avg_sq"))  # nothing was written


def test_a_row_left_alone_keeps_its_value_and_moments_where_dense_adam_moves_it(monkeypatch):
    monkeypatch.setenv(kernels.SWITCH, "off")  # the torch path, Adam's own operations: bit for bit
    param = torch.nn.Parameter(torch.zeros(3, 2))
    dense = torch.nn.Parameter(torch.zeros(3, 2))
    lazy_optimizer, dense_optimizer = LazyAdam([param], **SETTINGS), torch.optim.Adam([dense], **SETTINGS)
    first = sparse([[0, 2]], torch.ones(2, 2), (3, 2))
    param.grad, dense.grad = first, first.to_dense()
    lazy_optimizer.step(), dense_optimizer.step()
    after_first = param.detach().clone()
    second = sparse([[2]], torch.ones(1, 2), (3, 2))  # row 0 not touched
    param.grad, dense.grad = second, second.to_dense()
    lazy_optimizer.step(), dense_optimizer.step()
    assert torch.equal(param[0].detach(), after_first[0])  # lazy: row 0 stays
    assert (dense[0] < after_first[0]).all()  # dense Adam: its decaying momentum moves it on
    assert torch.equal(param[2].detach(), dense[2].detach())  # the row touched twice: the same update
    assert torch.equal(param[1].detach(), torch.zeros(2))


@pytest.mark.parametrize("fused", [False, pytest.param(True, marks=needs_kernel)])
def test_lazy_equals_dense_adam_when_every_row_is_touched_every_step(fused, monkeypatch):
    # the torch path bit for bit (Adam's own operations); the fused kernel to float32 rounding
    monkeypatch.setenv(kernels.SWITCH, "on" if fused else "off")
    same = (lambda a, b: torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7)) if fused else \
        (lambda a, b: torch.testing.assert_close(a, b, rtol=0, atol=0))
    shape = (3, 8, 2)
    start = torch.randn(shape, generator=torch.Generator().manual_seed(0))
    lazy, dense = torch.nn.Parameter(start.clone()), torch.nn.Parameter(start.clone())
    lazy_optimizer, dense_optimizer = LazyAdam([lazy], **SETTINGS), torch.optim.Adam([dense], **SETTINGS)
    generator = torch.Generator().manual_seed(1)
    rows = torch.cartesian_prod(torch.arange(3), torch.arange(8)).T  # [2, 24]: every row once
    for _ in range(5):
        order = torch.randperm(24, generator=generator)
        gradient = torch.sparse_coo_tensor(rows[:, order], torch.randn(24, 2, generator=generator), shape,
                                           check_invariants=True)
        lazy.grad, dense.grad = gradient, gradient.to_dense()
        lazy_optimizer.step(), dense_optimizer.step()
    assert (fused_kernel(lazy, lazy.detach()) is not None) == fused
    same(lazy.detach(), dense.detach())
    for key in ("step", "exp_avg", "exp_avg_sq"):
        same(lazy_optimizer.state[lazy][key], dense_optimizer.state[dense][key])
    assert not torch.equal(lazy.detach(), start)


def test_fused_lazy_adam_updates_sparse_rows_as_unfused_and_dense_parameters_as_fused_adam():
    generator = torch.Generator().manual_seed(0)
    start_table, start_dense = torch.randn(3, 8, 2, generator=generator), torch.randn(5, generator=generator)
    runs = []
    for optimizer_class, fused in ((LazyAdam, False), (LazyAdam, True), (torch.optim.Adam, True)):
        table, dense = torch.nn.Parameter(start_table.clone()), torch.nn.Parameter(start_dense.clone())
        optimizer = optimizer_class([dense] if optimizer_class is torch.optim.Adam else [table, dense],
                                    **SETTINGS, fused=fused)
        grads = torch.Generator().manual_seed(1)
        for _ in range(4):
            table.grad = sparse([[0, 2, 0], [1, 5, 1]], torch.randn(3, 2, generator=grads), table.shape)
            dense.grad = torch.randn(5, generator=grads)
            optimizer.step()
        runs.append((table.detach(), dense.detach()))
    (unfused_table, _), (fused_table, fused_dense), (_, adam_dense) = runs
    assert torch.equal(fused_table, unfused_table) and not torch.equal(fused_table, start_table)
    assert torch.equal(fused_dense, adam_dense)


def test_a_checkpoint_of_adam_continues_in_lazy_adam_and_back():
    generator = torch.Generator().manual_seed(0)
    start = torch.randn(4, 2, generator=generator)
    gradients = [torch.randn(4, 2, generator=generator) for _ in range(6)]
    reference = torch.nn.Parameter(start.clone())
    adam = torch.optim.Adam([reference], **SETTINGS)
    for g in gradients:  # six steps of Adam
        reference.grad = g
        adam.step()

    param = torch.nn.Parameter(start.clone())
    first = torch.optim.Adam([param], **SETTINGS)
    for g in gradients[:3]:  # three steps of Adam, saved
        param.grad = g
        first.step()
    checkpoint = first.state_dict()
    lazy = LazyAdam([param], **SETTINGS)
    lazy.load_state_dict(checkpoint)
    for g in gradients[3:5]:  # every row touched: the same steps as Adam's, here through sparse gradients
        param.grad = g.to_sparse(1)
        lazy.step()
    back = torch.optim.Adam([param], **SETTINGS)
    back.load_state_dict(lazy.state_dict())
    param.grad = gradients[5]
    back.step()
    assert torch.equal(param.detach(), reference.detach())
    assert back.state[param]["step"] == 6


@pytest.mark.parametrize(("options", "line"), [
    (dict(weight_decay=1e-6), "weight_decay=1e-06 [...] set weight_decay=0 for that group"),
    (dict(amsgrad=True), "amsgrad=True [...] set amsgrad=False for that group"),
])
def test_a_sparse_gradient_with_weight_decay_or_amsgrad_is_one_line(options, line):
    table, other = torch.nn.Parameter(torch.zeros(4, 2)), torch.nn.Parameter(torch.zeros(3))
    optimizer = LazyAdam([{"params": [other]}, {"params": [table], **options}], **SETTINGS)
    table.grad, other.grad = sparse([[1]], torch.ones(1, 2), (4, 2)), torch.ones(3)
    before, setting = line.split(" [...] ")
    with pytest.raises(ConfigError) as error:
        optimizer.step()
    message = str(error.value)
    assert message.startswith(f"LazyAdam: a sparse gradient (a parameter of shape [4, 2]) in a parameter group "
                              f"with {before}") and message.endswith(setting) and "\n" not in message
    assert not table.detach().any()


def test_summed_rows_take_sorted_unique_indices_as_they_are_and_coalesce_others():
    values = torch.tensor([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]])
    ordered = torch.sparse_coo_tensor(torch.tensor([[0, 1, 1], [2, 0, 3]]), values, (2, 4, 2), check_invariants=True)
    assert not ordered.is_coalesced()  # as autograd leaves a gradient, whatever its indices
    rows, held = summed_rows(ordered)
    assert rows.tolist() == [2, 4, 7] and held.data_ptr() == ordered._values().data_ptr()  # not copied
    repeated = sparse([[1, 0, 1], [3, 2, 3]], values, (2, 4, 2))  # row (1, 3) twice, out of order
    rows, held = summed_rows(repeated)
    assert rows.tolist() == [2, 7] and held.tolist() == [[3.0, 4.0], [6.0, 8.0]]


@pytest.mark.parametrize(("overrides", "optimizer", "sparse"), [
    (["encoding=hashgrid"], "torch.optim.Adam", False),  # opt-in until measured against dense Adam
    (["encoding=hashgrid", "encoding.position.sparse_gradients=true",
      "model.optimizer._target_=nerfexp.training.optimizers.LazyAdam"], "nerfexp.training.optimizers.LazyAdam", True),
    ([], "torch.optim.Adam", None),  # the paper's model: positional encoding, no table
    (["encoding=posenc", "scale=paper"], "torch.optim.Adam", None),
])
def test_the_configs_choose_their_optimizer_and_gradients(overrides, optimizer, sparse):
    with initialize_config_module("nerfexp.conf", version_base=None):
        cfg = compose("config", overrides=overrides)
    assert cfg.model.optimizer._target_ == optimizer and cfg.encoding.position.get("sparse_gradients") is sparse
    assert issubclass(get_class(optimizer), torch.optim.Adam)


@needs_kernel
def test_the_fused_lazy_update_follows_the_torch_path_over_many_steps(monkeypatch):
    # a hash table's shape: rows read many times per step, most rows untouched in each; ten steps, each row's
    # value and moments from the kernel within float32 rounding of the torch path's, untouched rows bit for bit
    shape = (4, 256, 2)
    start = torch.randn(shape, generator=torch.Generator().manual_seed(0))
    results = []
    for switch in ("on", "off"):
        monkeypatch.setenv(kernels.SWITCH, switch)
        param = torch.nn.Parameter(start.clone())
        optimizer = LazyAdam([param], lr=1e-2, betas=(0.9, 0.99), eps=1e-15)
        generator = torch.Generator().manual_seed(1)
        for _ in range(10):
            rows = torch.stack([torch.randint(0, 4, (300,), generator=generator),
                                torch.randint(0, 64, (300,), generator=generator)])  # rows 64.. never read
            param.grad = sparse(rows.tolist(), torch.randn(300, 2, generator=generator), shape)
            optimizer.step()
        results.append((param.detach(), optimizer.state[param]))
    (fused, fused_state), (reference, reference_state) = results
    torch.testing.assert_close(fused, reference, rtol=1e-5, atol=1e-7)
    for key in ("exp_avg", "exp_avg_sq"):
        torch.testing.assert_close(fused_state[key], reference_state[key], rtol=1e-5, atol=1e-7)  # gradients ~ 1
    assert torch.equal(fused[:, 64:], start[:, 64:]) and not fused_state["exp_avg"][:, 64:].any()
    assert not torch.equal(fused[:, :64], start[:, :64])
