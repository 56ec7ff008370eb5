"""Guards during training: a NaN or infinite loss or gradient, and a field collapsed to an empty or one-colour scene.

``TrainingGuard`` is a Lightning callback that looks at every optimizer step in
``on_before_optimizer_step``: after the backward pass (after gradient accumulation, and after mixed
precision has unscaled the gradients), before the update, the one point where a bad update can still
be dropped. It reads the module's ``diagnostics`` (per network, the batch's detached colour loss []
and opacity [B], see ``NeRFModule``) and the gradients.

A healthy step costs one device-to-host copy of a few numbers: the losses, each network's largest
opacity in the batch and the total gradient norm (``torch.nn.utils.get_total_norm``, the fused norms
``clip_grad_norm_`` takes; a NaN or inf in any entry makes the norm non-finite). Parameters are walked
by name only when that norm is not finite (finite gradients whose norm overflowed pass that walk).
A sparse gradient (a hash table's, ``HashGridEncoding(sparse_gradients=True)``) is checked by the entries
it holds (``held_entries``), its rows the batch touched.
With gradient accumulation, the losses and the batch seen are those of the last accumulated batch.

After each validation it reads each view's "contrast" (``NeRFModule._evaluate``; ``nerfexp.scoring.collapse``), a
number per view, gathered from every process in a distributed run.
"""

import logging
import math
from pathlib import Path

import lightning as L
import torch
from lightning.fabric.utilities import move_data_to_device
from torch import Tensor

from nerfexp.errors import FieldCollapseError, NonFiniteError
from nerfexp.scoring.collapse import blank_views
from nerfexp.training.checkpoints import save_whole
from nerfexp.training.guard_actions import COLLAPSE_ACTIONS, NONFINITE_ACTIONS

log = logging.getLogger(__name__)


def count_nonfinite(values: Tensor) -> str:
    """How ``values`` fail to be finite, e.g. "nan in 3 and infinite in 1" (of its entries)."""
    counts = {"nan": int(torch.isnan(values).sum()), "infinite": int(torch.isinf(values).sum())}
    return " and ".join(f"{kind} in {n}" for kind, n in counts.items() if n)


def held_entries(grad: Tensor) -> Tensor:
    """The entries a gradient holds: a dense gradient itself; a sparse COO one's values [nnz, ...] (its rows,
    repeated rows not summed where it is not coalesced). A NaN or infinity in the gradient is in them."""
    return grad._values() if grad.is_sparse else grad


def networks_phrase(names: list[str]) -> str:
    """"the fine network", "the coarse and fine networks"."""
    return f"the {' and '.join(names)} network{'s' if len(names) > 1 else ''}"


class TrainingGuard(L.Callback):
    """Stops (or skips the batch) on a non-finite loss or gradient; stops (or warns) on a collapsed field.

    Non-finite values: the message names the step, the quantity and the component, e.g.
    ``step 12: the gradient of renderer.fine.trunk.1.weight (fine network) is nan in 37 of 4096 entries;
    batch and weights saved to RUN_DIR/debug/nonfinite_step12.pt; the run stopped here``. A loss is
    named before any gradient (a NaN loss makes every gradient NaN), the coarse network before the
    fine one (the fine samples come from the coarse weights). The file (``torch.load(path,
    weights_only=True)``) holds ``step``, ``message``, the ``batch`` (its tensors), the module's
    ``state_dict`` before the update and the ``gradients`` by parameter name.

    Collapse: a network whose opacity stays below ``collapse_opacity`` on every ray of
    ``collapse_patience`` consecutive training batches renders an empty scene; a ReLU density that
    went negative everywhere has zero gradient and never comes back (on a white background the loss
    then sits at the empty scene's). And a validation after ``collapse_patience`` steps in which every view
    rendered nothing (``nerfexp.scoring.collapse.blank_views``: an empty or one-colour render, whatever opacity the
    rays keep) is a collapse: what a person sees, which a field that keeps a little opacity everywhere hides from
    the rule on opacity. The validation's scores are recorded before the run stops.

    With a gradient scaler (``trainer.precision=16-mixed``) infinite gradients are routine: the scaler
    skips those steps and lowers its scale. Only the losses are checked then.

    Args:
        dirpath: where debug files go; default ``TRAINER.default_root_dir/debug``.
        on_nonfinite: ``stop`` raises ``NonFiniteError``; ``skip`` drops the batch's update (no
            parameter or optimizer state changes), logs ``train/skipped_batches`` and goes on.
        max_skips: ``skip`` skips at most this many batches in a run; the next non-finite one stops it.
        on_collapse: ``stop`` raises ``FieldCollapseError``; ``warn`` logs the message once per network (and once
            for the validations).
        collapse_patience: consecutive empty batches that make a collapse; validations are judged from this
            step on (earlier ones may show an untrained field).
        collapse_opacity: a ray whose opacity is below this counts as empty.
    """

    def __init__(self, dirpath: str | None = None, on_nonfinite: str = "stop", max_skips: int = 10,
                 on_collapse: str = "stop", collapse_patience: int = 200, collapse_opacity: float = 1e-4):
        if on_nonfinite not in NONFINITE_ACTIONS:
            raise ValueError(f"guard on_nonfinite: expected one of {NONFINITE_ACTIONS}, got {on_nonfinite!r}")
        if on_collapse not in COLLAPSE_ACTIONS:
            raise ValueError(f"guard on_collapse: expected one of {COLLAPSE_ACTIONS}, got {on_collapse!r}")
        if max_skips < 0 or collapse_patience < 1:
            raise ValueError(f"guard: expected max_skips >= 0 and collapse_patience >= 1, got {max_skips} "
                             f"and {collapse_patience}")
        self.dirpath, self.on_nonfinite, self.max_skips = dirpath, on_nonfinite, max_skips
        self.on_collapse, self.collapse_patience = on_collapse, collapse_patience
        self.collapse_opacity = collapse_opacity
        self.skipped_batches = 0
        self.empty_batches: dict[str, int] = {}  # network -> consecutive batches with every ray empty
        self._reported_collapse: set[str] = set()  # the networks, and "validation", whose collapse was reported
        self._contrasts: dict[int, float] = {}  # view index -> its render's contrast, in this validation
        self._batch = None
        self._check_gradients = True

    def state_dict(self) -> dict:
        return {"skipped_batches": self.skipped_batches, "empty_batches": dict(self.empty_batches)}

    def load_state_dict(self, state_dict: dict) -> None:
        self.skipped_batches = state_dict["skipped_batches"]
        self.empty_batches = dict(state_dict["empty_batches"])

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        # a gradient scaler (16-mixed) skips the steps whose gradients overflow, and lowers its scale
        self._check_gradients = getattr(trainer.precision_plugin, "scaler", None) is None

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx: int) -> None:
        self._batch = batch  # a reference, saved only if the step goes wrong

    def on_before_optimizer_step(self, trainer: L.Trainer, pl_module: L.LightningModule,
                                 optimizer: torch.optim.Optimizer) -> None:
        diagnostics = pl_module.diagnostics
        names = list(diagnostics)
        losses = torch.stack([diagnostics[name]["loss"] for name in names])
        opacities = torch.stack([diagnostics[name]["opacity"].max() for name in names])
        grads = [held_entries(p.grad) for group in optimizer.param_groups for p in group["params"]
                 if p.grad is not None]
        if not self._check_gradients:
            grads = []
        grad_norm = torch.nn.utils.get_total_norm(grads) if grads else losses.new_zeros(())
        summary = torch.cat([losses, opacities, grad_norm[None]]).tolist()  # the step's one device-to-host copy
        loss_values = dict(zip(names, summary[:len(names)]))
        max_opacities = dict(zip(names, summary[len(names):-1]))

        problem = self._nonfinite(pl_module, loss_values, math.isfinite(summary[-1]))
        if problem is not None:
            self._stop_or_skip(trainer, pl_module, optimizer, problem)
        else:
            self._watch_collapse(trainer.global_step, max_opacities)
        if self.on_nonfinite == "skip":
            pl_module.log("train/skipped_batches", float(self.skipped_batches))

    def _nonfinite(self, pl_module: L.LightningModule, losses: dict[str, float], grads_finite: bool) -> str | None:
        """The first non-finite quantity of the step, described; None if all are finite."""
        bad_losses = [name for name, value in losses.items() if not math.isfinite(value)]
        if bad_losses:
            first, rest = bad_losses[0], bad_losses[1:]
            also = f" (the {' and '.join(rest)} network's too)" if rest else ""
            return f"the {first} network's colour loss is {losses[first]}{also}"
        if grads_finite:
            return None
        network_of = {p: name for name, net in pl_module.networks.items() for p in net.parameters()}
        bad = [(name, p) for name, p in pl_module.named_parameters()
               if p.grad is not None and not torch.isfinite(held_entries(p.grad)).all()]
        if not bad:  # finite entries whose 2-norm overflowed the dtype: nothing is NaN or infinite
            return None
        (name, p), rest = bad[0], bad[1:]
        where = f" ({network_of[p]} network)" if p in network_of else ""
        entries = held_entries(p.grad)
        held = " it holds (the rows the batch touched)" if p.grad.is_sparse else ""
        text = f"the gradient of {name}{where} is {count_nonfinite(entries)} of {entries.numel()} entries{held}"
        if rest:
            nets = [net for net in pl_module.networks if any(network_of.get(q) == net for _, q in rest)]
            text += f"; so are the gradients of {len(rest)} more parameter{'s' if len(rest) > 1 else ''}" + (
                f" (in {networks_phrase(nets)})" if nets else "")
        return text

    def _stop_or_skip(self, trainer: L.Trainer, pl_module: L.LightningModule, optimizer: torch.optim.Optimizer,
                      problem: str) -> None:
        step = trainer.global_step
        dirpath = Path(self.dirpath) if self.dirpath is not None else Path(trainer.default_root_dir) / "debug"
        path = dirpath / f"nonfinite_step{step}.pt"
        skip = self.on_nonfinite == "skip" and self.skipped_batches < self.max_skips
        if skip:
            outcome = f"batch skipped ({self.skipped_batches + 1} of at most {self.max_skips})"
        elif self.on_nonfinite == "skip":
            outcome = (f"{self.skipped_batches} batches skipped already, the most allowed "
                       f"(max_skips={self.max_skips}): the run stopped here")
        else:
            outcome = "the run stopped here"
        message = f"step {step}: {problem}; batch and weights saved to {path}; {outcome}"
        self._save(path, step, message, pl_module)
        if not skip:
            raise NonFiniteError(message)
        optimizer.zero_grad(set_to_none=True)  # a parameter without a gradient is left alone by the step
        self.skipped_batches += 1
        log.warning(message)

    def _save(self, path: Path, step: int, message: str, pl_module: L.LightningModule) -> None:
        """The batch, the weights and the gradients, on the CPU, loadable with ``weights_only=True``."""
        record = {
            "step": step, "message": message, "batch": move_data_to_device(self._batch, "cpu"),
            "state_dict": {key: value.cpu() for key, value in pl_module.state_dict().items()},
            "gradients": {name: p.grad.detach().cpu() for name, p in pl_module.named_parameters()
                          if p.grad is not None},
        }
        save_whole(record, path)

    def _watch_collapse(self, step: int, max_opacities: dict[str, float]) -> None:
        """Count each network's consecutive batches in which no ray reaches ``collapse_opacity``."""
        for name, opacity in max_opacities.items():
            self.empty_batches[name] = self.empty_batches.get(name, 0) + 1 if opacity < self.collapse_opacity else 0
        collapsed = [name for name in max_opacities if self.empty_batches[name] >= self.collapse_patience
                     and name not in self._reported_collapse]
        if not collapsed:
            return
        message = (f"step {step}: {networks_phrase(collapsed)} rendered nothing (opacity below "
                   f"{self.collapse_opacity:g} on every ray) for {self.collapse_patience} consecutive batches: "
                   "the density has collapsed to zero everywhere, and a ReLU density gets no gradient there to "
                   "recover. Try model.renderer.field.density_activation=softplus, a lower learning rate (scale.lr) "
                   "or a higher model.renderer.field.density_bias")
        if self.on_collapse == "stop":
            raise FieldCollapseError(message)
        self._reported_collapse.update(collapsed)
        log.warning(message)

    def on_validation_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: dict, batch,
                                batch_idx: int, dataloader_idx: int = 0) -> None:
        if not trainer.sanity_checking:
            self._contrasts[outputs["index"]] = outputs["contrast"]

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """After the validation (and the recorders' lines of it), where every view rendered nothing."""
        contrasts, self._contrasts = self._contrasts, {}
        step = trainer.global_step
        if trainer.sanity_checking or step < self.collapse_patience or "validation" in self._reported_collapse:
            return
        blank = blank_views(gathered_contrasts(trainer, pl_module, contrasts), "validation")
        if blank is None:
            return
        message = (f"step {step}: {blank}: the field shows no scene, however little opacity its rays keep. Training "
                   "views that disagree (poses some degrees off) can make an empty scene their closest fit; try "
                   "a lower learning rate (scale.lr) or a higher model.renderer.field.density_bias")
        if self.on_collapse == "stop":
            raise FieldCollapseError(message)
        self._reported_collapse.add("validation")
        if trainer.is_global_zero:  # every process judged the same views: one line says it
            log.warning(message)


def gathered_contrasts(trainer: L.Trainer, pl_module: L.LightningModule, contrasts: dict[int, float]
                       ) -> dict[int, float]:
    """Each validation view's contrast ``{index: contrast}``, this process's ``contrasts`` with those of every other
    process (a collective: every process calls it); a view that the distributed sampler gave two processes once."""
    if trainer.world_size == 1:
        return contrasts
    local = torch.tensor(list(contrasts.items()), dtype=torch.float64, device=pl_module.device).reshape(-1, 2)
    everyone = trainer.strategy.all_gather(local).reshape(-1, 2)  # [world size * views each, (index, contrast)]
    return {int(index): value for index, value in everyone.tolist()}
