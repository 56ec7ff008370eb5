"""Optimizers beyond torch's: ``LazyAdam``, Adam that also takes sparse gradients and updates only the rows
they hold (the hash grid's tables, ``nerfexp.nerf.hashgrid.HashGridEncoding(sparse_gradients=True)``).

Naming: a sparse gradient is a COO tensor of its parameter's shape [*S, *D], hybrid: its first
``sparse_dim()`` dims S are sparse (for a hash table [L_h, T, F]: level and row), the others D dense
(F); a "row" is one index into S, and ``values()`` [U, *D] hold the U rows it touches.
"""

import math

import torch
from torch import Tensor

from nerfexp.errors import ConfigError
from nerfexp.kernels import kernel


def flat_rows(indices: Tensor, sizes: torch.Size) -> Tensor:
    """Sparse indices [S, U] into dims of ``sizes`` (S of them) -> row-major flat indices [U].

    >>> flat_rows(torch.tensor([[0, 1], [2, 0]]), torch.Size([2, 3]))
    tensor([2, 3])
    """
    rows = indices[0]
    for dim in range(1, len(sizes)):
        rows = rows * sizes[dim] + indices[dim]
    return rows


def summed_rows(grad: Tensor) -> tuple[Tensor, Tensor]:
    """A sparse gradient [*S, *D] as its touched rows, each once and in ascending order: flat row indices
    [U] (``flat_rows``) and their summed values [U, *D]. Indices already so (``interpolate_rows`` makes them
    that way; autograd's accumulation drops the coalesced flag) are taken as they are, checked in one pass
    over them; others are coalesced (a sort). ``_indices()`` and ``_values()`` are what torch's sparse
    documentation gives for reading an uncoalesced COO tensor (``indices()`` refuses one; ``coalesce()`` sorts)."""
    sizes = grad.shape[:grad.sparse_dim()]
    rows = flat_rows(grad._indices(), sizes)
    if grad.is_coalesced() or bool((rows[1:] > rows[:-1]).all()):
        return rows, grad._values()
    grad = grad.coalesce()
    return flat_rows(grad.indices(), sizes), grad.values()


SPARSE_UPDATE_KERNEL = "lazy_adam"  # the fused kernel of ``lazy_adam_update``


def update_kernels(params: list[Tensor]) -> tuple[str, ...]:
    """The fused kernels a sparse gradient of ``params`` is updated with (``fused_kernel``'s condition on them):
    ``SPARSE_UPDATE_KERNEL`` where one is a contiguous float32 parameter on a CPU."""
    fused = any(p.device.type == "cpu" and p.dtype == torch.float32 and p.is_contiguous() for p in params)
    return (SPARSE_UPDATE_KERNEL,) if fused else ()


def fused_kernel(param: Tensor, values: Tensor):
    """The fused lazy update (``nerfexp.kernels``, lazy_adam.cpp) where it computes ``lazy_adam_update``: a
    contiguous float32 parameter and gradient on a CPU; else None, the torch path (the reference)."""
    if param.device.type != "cpu" or param.dtype != torch.float32 or values.dtype != torch.float32 \
            or not param.is_contiguous():
        return None
    return kernel(SPARSE_UPDATE_KERNEL)


def lazy_adam_update(param: Tensor, grad: Tensor, exp_avg: Tensor, exp_avg_sq: Tensor, step: float, lr: float,
                     beta1: float, beta2: float, eps: float) -> None:
    """Adam's update of the rows the sparse ``grad`` holds, in place; every other row of ``param``,
    ``exp_avg`` (m) and ``exp_avg_sq`` (v) is left as it is. With g a touched row's gradient (repeated
    rows summed, ``summed_rows``) and t = ``step`` (the parameter's count, this one included):

        m <- beta1 m + (1 - beta1) g,   v <- beta2 v + (1 - beta2) g^2,
        p <- p - lr / (1 - beta1^t) * m / (sqrt(v) / sqrt(1 - beta2^t) + eps)

    written with torch.optim.Adam's own operations (``lerp_``, ``addcmul_``, ``addcdiv_``), so that a
    gradient that touches every row updates the parameter as Adam does. On a CPU in float32 the fused kernel
    (``fused_kernel``) runs the same arithmetic in one pass over the rows; this torch path is its reference.
    param, exp_avg, exp_avg_sq [*S, *D] (contiguous), grad sparse COO [*S, *D]."""
    rows, values = summed_rows(grad)  # [U], [U, *D]
    dense_shape = param.shape[grad.sparse_dim():]
    fused = fused_kernel(param, values)
    if fused is not None:  # the same update in one pass over the rows (lazy_adam.cpp)
        width = math.prod(dense_shape)
        fused.rows(param.view(-1, width), exp_avg.view(-1, width), exp_avg_sq.view(-1, width), rows.long(),
                   values.reshape(-1, width).contiguous(), step, lr, beta1, beta2, eps)
        return

    def flat(tensor: Tensor) -> Tensor:
        return tensor.view(-1, *dense_shape)  # [rows, *D]

    m = flat(exp_avg).index_select(0, rows).lerp_(values, 1 - beta1)
    v = flat(exp_avg_sq).index_select(0, rows).mul_(beta2).addcmul_(values, values, value=1 - beta2)
    bias_correction1 = 1 - beta1**step
    bias_correction2 = 1 - beta2**step
    denom = (v.sqrt() / bias_correction2**0.5).add_(eps)
    updated = flat(param).index_select(0, rows).addcdiv_(m, denom, value=-lr / bias_correction1)
    flat(exp_avg).index_copy_(0, rows, m)
    flat(exp_avg_sq).index_copy_(0, rows, v)
    flat(param).index_copy_(0, rows, updated)


class LazyAdam(torch.optim.Adam):
    """torch.optim.Adam, which also takes sparse gradients (like torch.optim.SparseAdam and TensorFlow
    Addons' LazyAdam, in one optimizer with the dense parameters).

    A parameter with a dense gradient gets torch.optim.Adam's update, run by Adam's own ``step`` with the
    group's settings (fused, foreach, amsgrad, maximize, weight decay: whatever the group chose, bit for bit).
    A parameter with a sparse gradient gets the lazy update (``lazy_adam_update``): the rows in the gradient
    have their moments and values updated; the other rows keep theirs and do not move (dense Adam would go on
    moving a row by its decaying first moment after its last gradient). The bias correction uses the
    parameter's step count (the steps it had a gradient), as SparseAdam does.

    ``step`` uses torch's public API only: the lazy updates first, then ``torch.optim.Adam.step`` with the
    sparse gradients set aside (a parameter without a gradient is one Adam skips), then put back. Step hooks
    (``register_step_pre_hook``, ``register_step_post_hook``) run around the whole step, and once more around
    Adam's dense part where torch has wrapped ``torch.optim.Adam.step`` too (it does once an Adam is made).

    State: Adam's keys (``step``, ``exp_avg``, ``exp_avg_sq``; moments of the parameter's full shape), so
    a checkpoint of torch.optim.Adam loads into it and continues, and back. A sparse gradient in a
    group with ``weight_decay`` != 0 (decay changes every row) or ``amsgrad`` is refused (ConfigError), before
    any parameter moves.
    """

    def step(self, closure=None):
        """One step of every parameter with a gradient; ``closure`` (which recomputes the loss and the gradients)
        evaluated first, as Adam does. Returns the closure's loss (None without one)."""
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        sparse = [(group, p) for group in self.param_groups for p in group["params"]
                  if p.grad is not None and p.grad.is_sparse]
        for group, param in sparse:
            refuse_lazy_settings(group, param)
        grads = [param.grad for _, param in sparse]
        try:
            with torch.no_grad():
                for group, param in sparse:
                    lazy_step(self.state[param], group, param)
                    param.grad = None  # Adam's step skips it
            super().step()
        finally:
            for (_, param), grad in zip(sparse, grads, strict=True):
                param.grad = grad
        return loss


def refuse_lazy_settings(group: dict, param: Tensor) -> None:
    """A ConfigError where ``group`` sets what the lazy update has not (weight decay, amsgrad) for ``param``'s
    sparse gradient."""
    for key, off in (("weight_decay", 0), ("amsgrad", False)):
        if group[key] != off:
            raise ConfigError(f"LazyAdam: a sparse gradient (a parameter of shape {list(param.shape)}) in a "
                              f"parameter group with {key}={group[key]}: the lazy update has none; set "
                              f"{key}={off} for that group")


def lazy_step(state: dict, group: dict, param: Tensor) -> None:
    """One lazy update of ``param`` by its sparse gradient, with ``group``'s settings; ``state`` (the optimizer's
    for ``param``) made on the first, as Adam's: the step count a float tensor, the moments zeros of the
    parameter's shape."""
    if not state:
        scalar = torch.float64 if torch.get_default_dtype() == torch.float64 else torch.float32
        state["step"] = torch.tensor(0.0, dtype=scalar, device=param.device if group["capturable"] else "cpu")
        state["exp_avg"] = torch.zeros_like(param, memory_format=torch.contiguous_format)
        state["exp_avg_sq"] = torch.zeros_like(param, memory_format=torch.contiguous_format)
    state["step"] += 1
    beta1, beta2 = group["betas"]
    grad = -param.grad if group["maximize"] else param.grad
    lazy_adam_update(param, grad, state["exp_avg"], state["exp_avg_sq"], float(state["step"]), float(group["lr"]),
                     float(beta1), float(beta2), group["eps"])
