"""TrainingGuard in real Lightning training: NaNs and infinities at known steps, skipped batches, collapsed fields."""

import functools
import json
import logging
import math
import types

import lightning as L
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from lightning.pytorch.plugins.precision import MixedPrecision
from PIL import Image
from torch import nn
from torch.utils.data import DataLoader

from nerfexp.errors import FieldCollapseError, NonFiniteError
from nerfexp.nerf.fields import FieldOutputs
from nerfexp.nerf.hashgrid import HashGridEncoding
from nerfexp.nerf.hierarchy import HierarchyChoice
from nerfexp.nerf.volume_renderer import VolumeRenderer
from nerfexp.scoring.collapse import colour_spread
from nerfexp.training.guards import TrainingGuard, gathered_contrasts
from nerfexp.training.module import NeRFModule
from nerfexp.training.optimizers import LazyAdam
from tests.helpers import nan_targets, read_json, run_nerfexp


class LinearField(nn.Module):
    """rgb and sigma from one linear map of the position: parameters layer.weight [4, 3], layer.bias [4]."""

    def __init__(self, activation=F.softplus, density_bias=0.0):
        super().__init__()
        self.layer = nn.Linear(3, 4)
        self.activation, self.density_bias = activation, density_bias
        self.calls = 0

    def forward(self, positions, directions):
        self.calls += 1
        out = self.layer(positions)
        return FieldOutputs(rgb=torch.sigmoid(out[..., :3]), sigma=self.activation(out[..., 3] + self.density_bias))


class NaNFrom(LinearField):
    """A LinearField whose density is NaN from call ``first`` on, counting from 0: the renderer calls a
    network once per training step, so from step ``first``."""

    def __init__(self, first: int):
        super().__init__()
        self.first = first

    def forward(self, positions, directions):
        rgb, sigma, _ = super().forward(positions, directions)
        return FieldOutputs(rgb=rgb, sigma=sigma * (math.nan if self.calls > self.first else 1.0))


class EmptyBut(nn.Module):
    """Density exactly 0 except on every ``period``-th call (1 there): a field that is not collapsed."""

    def __init__(self, period: int):
        super().__init__()
        self.raw = nn.Parameter(torch.zeros(()))
        self.period, self.calls = period, 0

    def forward(self, positions, directions):
        self.calls += 1
        sigma = torch.full(positions.shape[:-1], float(self.calls % self.period == 0))
        return FieldOutputs(rgb=torch.sigmoid(self.raw).expand(*positions.shape[:-1], 3), sigma=sigma)


class HashField(nn.Module):
    """rgb and sigma from one linear map of a hash grid's features: a table position_encoding.hashed [2, 16, 2]
    (two hashed levels of 16 rows; with ``sparse_gradients``, a sparse gradient) and layer.weight [4, 4]."""

    def __init__(self, sparse_gradients: bool):
        super().__init__()
        self.position_encoding = HashGridEncoding(n_levels=2, log2_table_size=4, coarsest=4, finest=8, init_range=0.5,
                                                  aabb=[[-4.0] * 3, [4.0] * 3], sparse_gradients=sparse_gradients)
        self.layer = nn.Linear(4, 4)

    def forward(self, positions, directions):
        out = self.layer(self.position_encoding(positions))
        return FieldOutputs(rgb=torch.sigmoid(out[..., :3]), sigma=F.softplus(out[..., 3]))


def module(coarse: nn.Module, fine: nn.Module, optimizer=torch.optim.Adam) -> NeRFModule:
    fields = iter([coarse, fine])
    renderer = VolumeRenderer(lambda: next(fields),
                              HierarchyChoice(hierarchical=True, n_coarse=4, n_fine=4, n_single=8), near=2.0, far=6.0)
    return NeRFModule(renderer, functools.partial(optimizer, lr=1e-2), lr_final=1e-2)


def batches(n: int) -> list[dict]:
    generator = torch.Generator().manual_seed(0)
    out = []
    for _ in range(n):
        directions = F.normalize(torch.randn(8, 3, generator=generator), dim=-1)
        out.append({"origins": -4 * directions, "directions": directions, "rgb": torch.rand(8, 3, generator=generator)})
    return out


def views(n: int, side: int = 6) -> list[dict]:
    """``n`` validation views of ``side`` x ``side`` rays through the origin from 4 units away (each seen at its
    own turn about the y axis), whose targets are half black, half white."""
    u = torch.linspace(-0.3, 0.3, side)
    target = torch.zeros(side, side, 3)
    target[:, side // 2:] = 1.0
    out = []
    for index in range(n):
        turn = torch.tensor(0.5 * index)
        forward = torch.stack([torch.sin(turn), torch.tensor(0.0), torch.cos(turn)])
        right = torch.stack([torch.cos(turn), torch.tensor(0.0), -torch.sin(turn)])
        directions = F.normalize(forward + u[None, :, None] * right + u[:, None, None] * torch.tensor([0.0, 1, 0]),
                                 dim=-1)  # [side, side, 3]
        out.append({"origins": -4 * directions, "directions": directions, "rgb": target, "index": index})
    return out


def fit(m: NeRFModule, guard: TrainingGuard, steps: int, root, callbacks=(), val_every: int | None = None,
        **trainer_args) -> L.Trainer:
    """Train ``m`` for ``steps`` on ``batches``, validating on two ``views`` every ``val_every`` steps (None: never)."""
    torch.manual_seed(0)
    validation = {} if val_every is None else {"val_check_interval": val_every, "check_val_every_n_epoch": None,
                                               "num_sanity_val_steps": 0}
    trainer = L.Trainer(max_steps=steps, accelerator="cpu", logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, default_root_dir=root,
                        callbacks=[guard, *callbacks], **validation, **trainer_args)
    trainer.fit(m, train_dataloaders=DataLoader(batches(steps + 2), batch_size=None),
                val_dataloaders=None if val_every is None else DataLoader(views(2), batch_size=None))
    return trainer


def poison(parameter: nn.Parameter, trainer_of, steps: set[int]) -> None:
    """At ``steps``, the gradient of ``parameter`` gets nan in its first row and inf at [1, 0] (or nan
    everywhere for a vector)."""
    def hook(grad):
        if trainer_of().global_step not in steps:
            return grad
        grad = grad.clone()
        if grad.ndim == 2:
            grad[0], grad[1, 0] = math.nan, math.inf
        else:
            grad[:] = math.nan
        return grad
    parameter.register_hook(hook)


def poison_rows(table: nn.Parameter, trainer_of, steps: set[int]) -> None:
    """At ``steps``, the gradient of hash table ``table`` [L, T, F] (dense or sparse) gets nan in the first row
    the batch touched and inf in the first feature of the second (rows in row-major order)."""
    def hook(grad):
        if trainer_of().global_step not in steps:
            return grad
        if grad.is_sparse:
            grad = grad.coalesce()
            values = grad.values().clone()
            values[0], values[1, 0] = math.nan, math.inf
            return torch.sparse_coo_tensor(grad.indices(), values, grad.shape, check_invariants=True)
        grad = grad.clone()
        rows = grad.view(-1, grad.shape[-1])
        first, second = rows.any(-1).nonzero()[:2, 0].tolist()
        rows[first], rows[second, 0] = math.nan, math.inf
        return grad
    table.register_hook(hook)


class Snapshots(L.Callback):
    """Every parameter before and after each step: {step: (before, after)}."""

    def __init__(self):
        self.steps = {}

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self._before = {k: v.detach().clone() for k, v in pl_module.named_parameters()}

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        after = {k: v.detach().clone() for k, v in pl_module.named_parameters()}
        self.steps[trainer.global_step - 1] = (self._before, after)


def unchanged(before: dict, after: dict) -> bool:
    return all(torch.equal(before[k], after[k]) for k in before)


def test_a_nan_gradient_stops_naming_step_parameter_network_and_counts(tmp_path):
    torch.manual_seed(0)
    m = module(LinearField(), LinearField())
    initial = {k: v.clone() for k, v in m.state_dict().items()}
    poison(m.renderer.fine.layer.weight, lambda: m.trainer, {3})
    with pytest.raises(NonFiniteError) as error:
        fit(m, TrainingGuard(), 8, tmp_path)  # no dirpath: the trainer's default_root_dir/debug
    path = tmp_path / "debug" / "nonfinite_step3.pt"
    assert str(error.value) == (f"step 3: the gradient of renderer.fine.layer.weight (fine network) is nan in 3 "
                                f"and infinite in 1 of 12 entries; batch and weights saved to {path}; "
                                "the run stopped here")
    saved = torch.load(path, weights_only=True)
    assert saved["step"] == 3 and saved["message"] == str(error.value)
    for key, value in batches(10)[3].items():  # the fourth batch, the one of step 3
        assert torch.equal(saved["batch"][key], value)
    state = m.state_dict()  # stopped before the update: the weights the step would have changed
    assert saved["state_dict"].keys() == state.keys()
    assert all(torch.equal(saved["state_dict"][k], state[k]) for k in state)
    assert not all(torch.equal(saved["state_dict"][k], initial[k]) for k in state)  # three updates were made
    grad = saved["gradients"]["renderer.fine.layer.weight"]
    assert int(grad.isnan().sum()) == 3 and int(grad.isinf().sum()) == 1
    assert torch.isfinite(saved["gradients"]["renderer.coarse.layer.weight"]).all()


@pytest.mark.parametrize("sparse", [False, True])
def test_a_nan_in_a_hash_tables_gradient_stops_dense_or_sparse(tmp_path, sparse):
    torch.manual_seed(0)
    m = module(HashField(sparse), HashField(sparse), LazyAdam)
    table = m.renderer.fine.position_encoding.hashed
    poison_rows(table, lambda: m.trainer, {2})
    with pytest.raises(NonFiniteError) as error:
        fit(m, TrainingGuard(), 5, tmp_path)
    path = tmp_path / "debug" / "nonfinite_step2.pt"
    grad = torch.load(path, weights_only=True)["gradients"]["renderer.fine.position_encoding.hashed"]
    assert grad.is_sparse == sparse and grad.shape == (2, 16, 2)
    held = grad._values() if sparse else grad  # sparse: the rows the batch touched (fewer than the table's 32)
    assert int(held.isnan().sum()) == 2 and int(held.isinf().sum()) == 1
    entries = f"{held.numel()} entries it holds (the rows the batch touched)" if sparse else "64 entries"
    assert str(error.value) == (f"step 2: the gradient of renderer.fine.position_encoding.hashed (fine network) is "
                                f"nan in 2 and infinite in 1 of {entries}; batch and weights saved to {path}; "
                                "the run stopped here")
    assert not sparse or held.numel() < 64


def test_a_skipped_batch_leaves_a_sparse_table_and_its_moments_alone(tmp_path):
    torch.manual_seed(0)
    m = module(HashField(True), HashField(True), LazyAdam)
    table = m.renderer.fine.position_encoding.hashed
    poison_rows(table, lambda: m.trainer, {2})
    snapshots = Snapshots()
    trainer = fit(m, TrainingGuard(on_nonfinite="skip"), 4, tmp_path, callbacks=[snapshots])
    assert [step for step, (before, after) in sorted(snapshots.steps.items()) if unchanged(before, after)] == [2]
    assert trainer.optimizers[0].state[table]["step"] == 3


def test_several_bad_gradients_name_the_first_and_count_the_rest(tmp_path):
    torch.manual_seed(0)
    m = module(LinearField(), LinearField())
    poison(m.renderer.coarse.layer.bias, lambda: m.trainer, {1})
    poison(m.renderer.fine.layer.weight, lambda: m.trainer, {1})
    with pytest.raises(NonFiniteError, match=r"^step 1: the gradient of renderer\.coarse\.layer\.bias \(coarse "
                       r"network\) is nan in 4 of 4 entries; so are the gradients of 1 more parameter \(in the "
                       r"fine network\); batch and weights saved to .*nonfinite_step1\.pt; the run stopped here$"):
        fit(m, TrainingGuard(dirpath=str(tmp_path / "elsewhere")), 4, tmp_path)
    assert (tmp_path / "elsewhere" / "nonfinite_step1.pt").exists()


def test_a_nan_loss_is_named_by_network_before_its_gradients(tmp_path):
    torch.manual_seed(0)
    m = module(LinearField(), NaNFrom(2))  # the fine network's density is nan from step 2 on
    with pytest.raises(NonFiniteError, match=r"^step 2: the fine network's colour loss is nan; batch and weights "
                       r"saved to .*nonfinite_step2\.pt; the run stopped here$"):
        fit(m, TrainingGuard(), 6, tmp_path)
    saved = torch.load(tmp_path / "debug" / "nonfinite_step2.pt", weights_only=True)
    assert not torch.isfinite(saved["gradients"]["renderer.fine.layer.weight"]).all()


def test_skip_drops_exactly_the_bad_batches_and_counts_them(tmp_path):
    torch.manual_seed(0)
    m = module(LinearField(), LinearField())
    poison(m.renderer.fine.layer.weight, lambda: m.trainer, {2, 4})
    snapshots, guard = Snapshots(), TrainingGuard(on_nonfinite="skip", max_skips=2)
    trainer = fit(m, guard, 7, tmp_path, callbacks=[snapshots])
    assert trainer.global_step == 7 and guard.skipped_batches == 2
    assert trainer.callback_metrics["train/skipped_batches"] == 2
    assert [step for step, (before, after) in sorted(snapshots.steps.items()) if unchanged(before, after)] == [2, 4]
    adam = trainer.optimizers[0]
    assert adam.state[m.renderer.fine.layer.weight]["step"] == 5  # Adam's moments skipped the two batches too
    assert sorted(p.name for p in (tmp_path / "debug").iterdir()) == ["nonfinite_step2.pt", "nonfinite_step4.pt"]


def test_skip_stops_after_max_skips(tmp_path):
    torch.manual_seed(0)
    m = module(LinearField(), LinearField())
    poison(m.renderer.fine.layer.weight, lambda: m.trainer, {1, 2, 3})
    with pytest.raises(NonFiniteError, match=r"^step 3: the gradient of renderer\.fine\.layer\.weight .*; 2 batches "
                       r"skipped already, the most allowed \(max_skips=2\): the run stopped here$"):
        fit(m, TrainingGuard(on_nonfinite="skip", max_skips=2), 6, tmp_path)


def test_a_gradient_scaler_owns_infinite_gradients(tmp_path):
    # With a scaler (16-mixed on GPUs) infinite gradients are routine: the scaler skips the step.
    torch.manual_seed(0)
    m = module(LinearField(), LinearField())
    poison(m.renderer.fine.layer.weight, lambda: m.trainer, {1})
    snapshots = Snapshots()
    amp = MixedPrecision("16-mixed", "cpu", scaler=torch.amp.GradScaler("cpu"))
    trainer = fit(m, TrainingGuard(), 3, tmp_path, callbacks=[snapshots], plugins=[amp])
    assert trainer.global_step == 3 and unchanged(*snapshots.steps[1]) and not unchanged(*snapshots.steps[2])


COLLAPSE = r"the coarse and fine networks rendered nothing \(opacity below 0.0001 on every ray\) for 5 consecutive"


def dead_relu() -> LinearField:
    return LinearField(F.relu, density_bias=-1000.0)  # sigma = relu(raw - 1000): exactly 0, zero gradient


def test_a_collapsed_field_stops_after_patience_batches(tmp_path):
    torch.manual_seed(0)
    m = module(dead_relu(), dead_relu())
    with pytest.raises(FieldCollapseError, match=rf"^step 4: {COLLAPSE} batches: .* Try "
                       r"model\.renderer\.field\.density_activation=softplus"):
        fit(m, TrainingGuard(collapse_patience=5), 20, tmp_path)
    assert m.trainer.global_step == 4


def test_a_collapsed_field_warns_once_and_trains_on(tmp_path, caplog):
    torch.manual_seed(0)
    m = module(dead_relu(), dead_relu())
    with caplog.at_level(logging.WARNING, logger="nerfexp.training.guards"):
        trainer = fit(m, TrainingGuard(on_collapse="warn", collapse_patience=5), 12, tmp_path)
    assert trainer.global_step == 12
    warnings = [r.getMessage() for r in caplog.records if r.name == "nerfexp.training.guards"]
    assert len(warnings) == 1 and warnings[0].startswith("step 4: the coarse and fine networks rendered nothing")


@pytest.mark.parametrize("period, patience, flagged", [(3, 3, False), (3, 2, True)])
def test_collapse_needs_consecutive_empty_batches(tmp_path, period, patience, flagged):
    # EmptyBut(3): empty at steps 0, 1, then opaque at 2, empty at 3, 4, ...: two empty batches in a row at most
    m = module(EmptyBut(period), EmptyBut(period))
    guard = TrainingGuard(collapse_patience=patience)
    if flagged:
        with pytest.raises(FieldCollapseError, match=r"^step 1: the coarse and fine networks rendered nothing"):
            fit(m, guard, 9, tmp_path)
    else:
        assert fit(m, guard, 9, tmp_path).global_step == 9


def test_a_healthy_field_is_not_flagged(tmp_path):
    torch.manual_seed(0)
    m = module(LinearField(), LinearField())
    guard = TrainingGuard(collapse_patience=1)  # one batch with every ray empty would be enough
    assert fit(m, guard, 6, tmp_path).global_step == 6
    assert guard.empty_batches == {"coarse": 0, "fine": 0} and guard.skipped_batches == 0


class Fog(nn.Module):
    """An even fog of density ``sigma`` and one colour (grey, a parameter): every ray keeps the same opacity, far
    above any "empty" threshold on opacity, and the render is one colour: no scene."""

    def __init__(self, sigma: float):
        super().__init__()
        self.raw = nn.Parameter(torch.zeros(()))
        self.sigma = sigma

    def forward(self, positions, directions):
        rgb = torch.sigmoid(self.raw).expand(*positions.shape[:-1], 3)
        return FieldOutputs(rgb=rgb, sigma=torch.full(positions.shape[:-1], self.sigma) + 0 * self.raw)


VALIDATION_COLLAPSE = (r"every validation view rendered nothing \(2 views: an empty or one-colour image each, its "
                       r"colours' spread at most 0\.0% of its target's, below 1%\): the field shows no scene")


@pytest.mark.parametrize("sigma", [1e-3, 0.5])  # opacity about 0.004 on every ray, or 0.86: neither is empty
def test_an_even_fog_stops_at_the_first_validation_from_patience_on(tmp_path, sigma):
    m = module(Fog(sigma), Fog(sigma))
    guard = TrainingGuard(collapse_patience=3)
    with pytest.raises(FieldCollapseError, match=rf"^step 4: {VALIDATION_COLLAPSE}, however little opacity its rays "
                       r"keep\. .*scale\.lr"):
        fit(m, guard, 10, tmp_path, val_every=2)  # the validation of step 2 comes before the patience: not judged
    assert m.trainer.global_step == 4
    assert guard.empty_batches == {"coarse": 0, "fine": 0}  # the rule on opacity saw rays that were not empty


def test_an_even_fog_warns_once_and_trains_on(tmp_path, caplog):
    m = module(Fog(1e-3), Fog(1e-3))
    with caplog.at_level(logging.WARNING, logger="nerfexp.training.guards"):
        trainer = fit(m, TrainingGuard(on_collapse="warn", collapse_patience=3), 10, tmp_path, val_every=2)
    assert trainer.global_step == 10
    warnings = [r.getMessage() for r in caplog.records if r.name == "nerfexp.training.guards"]
    assert len(warnings) == 1 and warnings[0].startswith("step 4: every validation view rendered nothing (2 views")


def test_validations_before_the_patience_are_not_judged(tmp_path):
    # an untrained field may render a fog: the first validations say nothing until it had patience steps to learn
    m = module(Fog(1e-3), Fog(1e-3))
    assert fit(m, TrainingGuard(collapse_patience=100), 8, tmp_path, val_every=2).global_step == 8


def test_a_field_that_renders_a_scene_is_not_flagged_at_any_validation(tmp_path):
    torch.manual_seed(0)
    m = module(LinearField(), LinearField())
    renders = []

    class Renders(L.Callback):
        def on_validation_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0):
            renders.append(outputs["rgb"])

    assert fit(m, TrainingGuard(collapse_patience=1), 6, tmp_path, callbacks=[Renders()], val_every=1).global_step == 6
    assert len(renders) == 12 and all(colour_spread(r) > 0.01 * colour_spread(views(1)[0]["rgb"]) for r in renders)


def test_each_view_is_judged_once_whichever_processes_scored_it():
    def all_gather(tensor):  # two processes; the distributed sampler gave both view 2 (its padding)
        return torch.stack([tensor, torch.tensor([[1.0, 0.5], [2.0, 0.25]], dtype=torch.float64)])

    trainer = types.SimpleNamespace(world_size=2, strategy=types.SimpleNamespace(all_gather=all_gather))
    module_ = types.SimpleNamespace(device=torch.device("cpu"))
    gathered = gathered_contrasts(trainer, module_, {0: 0.125, 2: 0.25})
    assert gathered == {0: 0.125, 1: 0.5, 2: 0.25}
    single = types.SimpleNamespace(world_size=1)
    assert gathered_contrasts(single, module_, {3: 0.5}) == {3: 0.5}


def test_options_are_checked():
    with pytest.raises(ValueError, match="on_nonfinite"):
        TrainingGuard(on_nonfinite="ignore")
    with pytest.raises(ValueError, match="on_collapse"):
        TrainingGuard(on_collapse="skip")


def test_a_nan_run_ends_with_one_line_naming_step_and_network(tmp_path, tiny):
    # a density bias of nan would do it too, but the settings check refuses it before any step
    result = run_nerfexp(*tiny, *nan_targets(), f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    path = tmp_path / "debug" / "nonfinite_step0.pt"
    assert result.returncode == 1 and "Traceback" not in result.stderr
    errors = [line for line in result.stderr.splitlines() if line.startswith("nerfexp: error:")]
    assert errors == [f"nerfexp: error: step 0: the coarse network's colour loss is nan (the fine network's too); "
                      f"batch and weights saved to {path}; the run stopped here"]
    saved = torch.load(path, weights_only=True)
    assert saved["step"] == 0 and saved["batch"]["rgb"].shape == (256, 3)  # scale.batch_rays=256
    weights = saved["state_dict"]  # finite: the nan comes from the targets, not a weight
    assert any(k.startswith("renderer.fine.") for k in weights) and all(v.isfinite().all() for v in weights.values())


def test_a_collapsed_relu_run_ends_with_the_collapse_message(tmp_path, tiny):
    result = run_nerfexp(*tiny, "model.renderer.field.density_activation=relu",
                         "model.renderer.field.density_bias=-80", "callbacks.guard.collapse_patience=10",
                         f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    assert result.returncode == 1 and "Traceback" not in result.stderr
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("nerfexp: error: step 9: the coarse and fine networks rendered nothing (opacity below "
                           "0.0001 on every ray) for 10 consecutive batches")
    assert "density_activation=softplus" in last


# softplus(raw - 8): a fog of about 0.2% opacity on every ray, twenty times the rule on opacity's 1e-4, and one colour
FOG = ["model.renderer.field.density_bias=-8", "callbacks.guard.collapse_patience=10"]


def test_a_run_that_renders_a_fog_stops_at_its_first_validation_in_one_line(tmp_path, tiny):
    result = run_nerfexp(*tiny, *FOG, f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    assert result.returncode == 1 and "Traceback" not in result.stderr
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("nerfexp: error: step 30: every validation view rendered nothing (1 view: an empty or "
                           "one-colour image each, its colours' spread at most 0.0% of its target's, below 1%)")
    status = read_json(tmp_path / "status.json")
    assert status["state"] == "failed" and status["error"] == f"FieldCollapseError: {last[len('nerfexp: error: '):]}"
    validations = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    # recorded before the run stopped, after the test views' scores at the default budgets (steps 15 and 30)
    assert [(r["step"], r["split"]) for r in validations] == [(15, "test"), (30, "test"), (30, "val")]
    assert not (tmp_path / "results.json").exists()


def test_a_fog_run_that_warns_finishes_recorded_as_collapsed(tmp_path, tiny):
    run_dir = tmp_path / "run"
    result = run_nerfexp(*tiny, *FOG, "callbacks.guard.on_collapse=warn", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    for view in (0, 1):  # what a person sees: each test image is one colour
        pixels = np.asarray(Image.open(run_dir / "test" / f"r_{view}.png")).reshape(-1, 3)
        assert len(np.unique(pixels, axis=0)) == 1
    line = ("every test view rendered nothing (2 views: an empty or one-colour image each, its colours' spread at "
            "most 0.0% of its target's, below 1%)")
    assert read_json(run_dir / "results.json")["collapse"] == line
    status = read_json(run_dir / "status.json")
    assert (status["state"], status["collapse"]) == ("finished", line)
    output = result.stdout + result.stderr
    assert output.count("step 30: every validation view rendered nothing") == 1  # warned once, at the first
    assert f"scores of a render of nothing: {line} after 60 steps" in output
    evaluation = run_nerfexp(str(run_dir), cwd=tmp_path, script="nerfexp-eval")
    assert evaluation.returncode == 0 and f"scores of a render of nothing: {line} of " in evaluation.stdout
    assert read_json(run_dir / "eval.json")["collapse"] == line


def test_a_run_that_learns_is_not_recorded_as_collapsed(tiny_run):
    assert read_json(tiny_run / "results.json")["collapse"] is None
    status = read_json(tiny_run / "status.json")
    assert (status["state"], status["collapse"]) == ("finished", None)
