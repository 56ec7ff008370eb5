import csv
import functools
import hashlib
import math
from pathlib import Path
from unittest import mock

import lightning as L
import pytest
import torch
from lightning.pytorch.loggers import CSVLogger
from torch import nn
from torch.utils.data import DataLoader

from nerfexp.errors import ConfigError
from nerfexp.nerf.encodings import PositionalEncoding
from nerfexp.nerf.fields import DensityField, FieldOutputs, MLPViewDependence, NeRFField
from nerfexp.nerf.hashgrid import HashGridEncoding
from nerfexp.nerf.hierarchy import HierarchyChoice
from nerfexp.nerf.proposal import ProposalSampler
from nerfexp.nerf.volume_renderer import VolumeRenderer
from nerfexp.training.module import NeRFModule, seeded_random


class OpaqueField(nn.Module):
    """Of one colour, opaque from the first sample on: sigma 1e6 over the ray's length of at least 3 gives an
    optical depth of 3e6, and exp(-3e6) is 0 in float32, so the ray's opacity is 1 and its colour the field's."""

    def __init__(self, colour: float):
        super().__init__()
        self.colour = nn.Parameter(torch.tensor(colour))

    def forward(self, positions, directions):
        sigma = torch.full(positions.shape[:-1], 1e6)
        return FieldOutputs(rgb=self.colour.expand(*sigma.shape, 3), sigma=sigma)


class ConstantField(nn.Module):
    def __init__(self):
        super().__init__()
        self.raw = nn.Parameter(torch.zeros(()))

    def forward(self, positions, directions):
        sigma = nn.functional.softplus(self.raw).expand(positions.shape[:-1])
        return FieldOutputs(rgb=torch.sigmoid(self.raw).expand(*positions.shape[:-1], 3), sigma=sigma)


def module(field, lr=1e-3, lr_final=1e-4, lr_warmup_steps=0):
    renderer = VolumeRenderer(field, HierarchyChoice(hierarchical=True, n_coarse=4, n_fine=4, n_single=12), near=2.0,
                              far=6.0)
    return NeRFModule(renderer, functools.partial(torch.optim.Adam, lr=lr), lr_final=lr_final, chunk=7,
                      lr_warmup_steps=lr_warmup_steps)


def batch(n=8):
    directions = torch.nn.functional.normalize(torch.randn(n, 3), dim=-1)
    return {"origins": -4 * directions, "directions": directions, "rgb": torch.rand(n, 3)}


def test_training_exposes_each_networks_loss_and_opacity_detached():
    torch.manual_seed(0)
    fields = iter([OpaqueField(0.25), OpaqueField(0.75)])
    m, b = module(lambda: next(fields)), batch(8)
    trainer = L.Trainer(max_steps=1, accelerator="cpu", logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False)
    trainer.fit(m, train_dataloaders=DataLoader([b], batch_size=None))
    # Every ray renders its network's colour (the weights before the step's update): MSE against the target.
    for name, colour in (("coarse", 0.25), ("fine", 0.75)):
        figures = m.diagnostics[name]
        torch.testing.assert_close(figures["loss"], ((colour - b["rgb"]) ** 2).mean())
        torch.testing.assert_close(figures["opacity"], torch.ones(8))
        assert not figures["loss"].requires_grad and not figures["opacity"].requires_grad


def test_networks_are_named_as_the_renderer_outputs():
    m = module(ConstantField)
    assert m.networks == {"coarse": m.renderer.coarse, "fine": m.renderer.fine}
    flat = NeRFModule(VolumeRenderer(ConstantField, HierarchyChoice(False, n_coarse=4, n_fine=4, n_single=8), near=2.0,
                                     far=6.0), functools.partial(torch.optim.Adam, lr=1e-3), lr_final=1e-4)
    assert flat.networks == {"coarse": flat.renderer.coarse}


def hash_grid_module(hierarchical, sparse_gradients=False) -> NeRFModule:
    """Fields and proposal networks on small hash grids: the tables in every network's copy of the encoding."""
    grid = HashGridEncoding(n_levels=3, log2_table_size=6, coarsest=2, finest=16, aabb=[[-1.0] * 3, [1.0] * 3],
                            sparse_gradients=sparse_gradients)
    head = functools.partial(MLPViewDependence, direction_encoding=PositionalEncoding(2), hidden=8)
    field = functools.partial(NeRFField, grid, head, depth=2, width=8, skips=())
    proposal = functools.partial(ProposalSampler, functools.partial(DensityField, grid, depth=1, width=8, skips=()),
                                 n_samples=[8], n_final=8)
    renderer = VolumeRenderer(field, HierarchyChoice(hierarchical, 8, 8, 8, proposal=proposal), near=2.0, far=6.0)
    return NeRFModule(renderer, functools.partial(torch.optim.Adam, lr=1e-3, weight_decay=1e-6), lr_final=1e-4)


@pytest.mark.parametrize("hierarchical", [True, False, "proposal"])
def test_every_parameter_lands_in_exactly_one_group_named_by_its_component(hierarchical):
    m = hash_grid_module(hierarchical)
    groups = m.named_parameter_groups()
    assert list(groups) == ["networks", "hash_tables"] and groups["hash_tables"]["weight_decay"] == 0.0
    assert set(groups["networks"]) == {"params"}  # the optimizer's own options
    order = [id(p) for p in m.parameters()]
    placed = [id(p) for group in groups.values() for p in group["params"]]
    assert sorted(placed) == sorted(order)  # each parameter once
    for group in groups.values():  # in parameters()' order, as the optimizer's state was laid out before
        ids = [id(p) for p in group["params"]]
        assert ids == [i for i in order if i in set(ids)]
    # the tables of every copy: one per field, and one per proposal network
    tables = {id(p) for module in m.modules() if isinstance(module, HashGridEncoding) for p in module.parameters()}
    copies = {True: 2, False: 1, "proposal": 2}[hierarchical]
    assert {id(p) for p in groups["hash_tables"]["params"]} == tables and len(tables) == 2 * copies
    optimizer = m.optimizer(m.parameter_groups())
    assert [g["weight_decay"] for g in optimizer.param_groups] == [1e-6, 0.0]
    # without a trainable encoding, the networks alone
    assert list(module(ConstantField).named_parameter_groups()) == ["networks"]


@pytest.mark.parametrize(("world_size", "sparse"), [(1, True), (2, False)])
def test_several_processes_make_the_encodings_sparse_gradients_dense(world_size, sparse):
    m = hash_grid_module(True, sparse_gradients=True)
    m.trainer = L.Trainer(logger=False, enable_checkpointing=False, enable_progress_bar=False)
    with mock.patch.object(L.Trainer, "world_size", world_size):
        m.on_fit_start()
    grids = [module for module in m.modules() if isinstance(module, HashGridEncoding)]
    assert len(grids) == 2 and all(g.sparse_gradients is sparse for g in grids)


def learning_rates(m: NeRFModule, steps: int) -> list[float]:
    m.trainer = L.Trainer(max_steps=steps, logger=False, enable_checkpointing=False, enable_progress_bar=False)
    config = m.configure_optimizers()
    optimizer, schedule = config["optimizer"], config["lr_scheduler"]["scheduler"]
    lrs = []
    for _ in range(steps + 1):
        lrs.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        schedule.step()
    return lrs


def test_learning_rate_decays_exponentially_to_lr_final_over_max_steps():
    lrs = learning_rates(module(ConstantField, lr=5e-4, lr_final=5e-5), 100)
    assert lrs[0] == pytest.approx(5e-4) and lrs[50] == pytest.approx(5e-4 * 0.1 ** 0.5)
    assert lrs[100] == pytest.approx(5e-5)


def test_warmup_ramps_linearly_then_follows_the_decay():
    # step s < 10: (s + 1) / 10 of the decayed rate 5e-3 * 0.1^(s / 100); from step 9 on, the decay alone
    lrs = learning_rates(module(ConstantField, lr=5e-3, lr_final=5e-4, lr_warmup_steps=10), 100)
    assert lrs[0] == pytest.approx(5e-4) and lrs[4] == pytest.approx(0.5 * 5e-3 * 0.1 ** 0.04)
    assert lrs[50] == pytest.approx(5e-3 * 0.1 ** 0.5) and lrs[100] == pytest.approx(5e-4)


def test_image_rendering_in_chunks_equals_rendering_at_once():
    torch.manual_seed(0)
    m = module(ConstantField)
    with torch.no_grad():
        m.renderer.coarse.raw.fill_(0.3)
        m.renderer.fine.raw.fill_(-0.2)
    b = batch(15)
    image = m.render_image(b["origins"].reshape(3, 5, 3), b["directions"].reshape(3, 5, 3))  # chunks of 7
    whole = m.renderer(b["origins"], b["directions"], deterministic=True)["fine"]
    torch.testing.assert_close(image["rgb"].reshape(15, 3), whole["rgb"])
    torch.testing.assert_close(image["depth"].reshape(15), whole["depth"])


def test_denormals_are_flushed_during_fit_only_and_restored_after_a_failure():
    from torch.utils.data import DataLoader

    from nerfexp.training.callbacks import FlushDenormals, flushes_denormals

    class Probe(L.Callback):
        def __init__(self, fail: bool):
            self.fail, self.seen = fail, []

        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
            self.seen.append(flushes_denormals())
            if self.fail:
                raise RuntimeError("stop here")

    assert not flushes_denormals()  # IEEE arithmetic: tiny / 2 is a denormal, not 0
    for fail in (False, True):
        probe = Probe(fail)
        trainer = L.Trainer(max_steps=2, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                            enable_model_summary=False, limit_val_batches=0, callbacks=[FlushDenormals(), probe])
        loader = DataLoader([batch()] * 2, batch_size=None)
        if fail:
            with pytest.raises(RuntimeError, match="stop here"):
                trainer.fit(module(ConstantField), train_dataloaders=loader)
        else:
            trainer.fit(module(ConstantField), train_dataloaders=loader)
        assert probe.seen and all(probe.seen)  # flushed while training
        assert not flushes_denormals()  # and restored afterwards


def test_a_launcher_jobs_sigterm_handler_stays_in_place_of_lightnings_while_it_trains():
    import signal

    from torch.utils.data import DataLoader

    from nerfexp.training.callbacks import KeepSigtermHandler

    def ours(signum, frame):  # stands in for nerfexp.commands.signals' handler
        raise AssertionError("never called here")

    class Probe(L.Callback):
        def __init__(self):
            self.seen = []

        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
            self.seen.append(signal.getsignal(signal.SIGTERM))

    previous = signal.signal(signal.SIGTERM, ours)
    try:
        for keep in (False, True):
            probe = Probe()
            trainer = L.Trainer(max_steps=2, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                                enable_model_summary=False, limit_val_batches=0,
                                callbacks=[probe, *([KeepSigtermHandler()] if keep else [])])
            trainer.fit(module(ConstantField), train_dataloaders=DataLoader([batch()] * 2, batch_size=None))
            # Lightning's own handler while it trains, unless the callback put ours back; ours after fit
            assert all((handler is ours) == keep for handler in probe.seen) and len(probe.seen) == 2
            assert signal.getsignal(signal.SIGTERM) is ours
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_a_seeded_block_repeats_its_numbers_and_leaves_the_global_stream_alone():
    before = torch.get_rng_state()
    with seeded_random(5, torch.device("cpu")):
        first = torch.rand(4)
    assert torch.equal(torch.get_rng_state(), before)
    with seeded_random(5, torch.device("cpu")):
        again = torch.rand(4)
    with seeded_random(6, torch.device("cpu")):
        other = torch.rand(4)
    with seeded_random(None, torch.device("cpu")):  # no seed: the global stream itself
        unseeded = torch.rand(4)
    assert torch.equal(first, again) and not torch.equal(first, other)
    torch.set_rng_state(before)
    assert torch.equal(unseeded, torch.rand(4))


def test_bf16_mixed_training_keeps_rendering_in_float32(monkeypatch):
    # A real training run under Lightning's bf16-mixed precision on the CPU: the network's matrix
    # products run in bf16, yet every rendering call gets float32 densities, and training stays finite.
    import lightning as L
    from torch.utils.data import DataLoader

    import nerfexp.nerf.volume_renderer as renderer_module
    from nerfexp.nerf.encodings import PositionalEncoding
    from nerfexp.nerf.fields import MLPViewDependence, NeRFField
    from nerfexp.training.module import NeRFModule

    rendered_dtypes = []
    original = renderer_module.render_weights

    def recording_render_weights(sigmas, t_starts, t_ends):
        rendered_dtypes.append(sigmas.dtype)
        return original(sigmas, t_starts, t_ends)

    monkeypatch.setattr(renderer_module, "render_weights", recording_render_weights)
    head = functools.partial(MLPViewDependence, direction_encoding=PositionalEncoding(2), hidden=16)
    field = functools.partial(NeRFField, PositionalEncoding(4), head, depth=3, width=32, skips=(1,),
                              density_activation="softplus", density_bias=-1.0)
    torch.manual_seed(0)
    renderer = VolumeRenderer(field, HierarchyChoice(hierarchical=True, n_coarse=8, n_fine=8, n_single=16), near=2.0,
                              far=6.0)
    network_dtypes = set()
    renderer.coarse.trunk[0].register_forward_hook(lambda m, i, out: network_dtypes.add(out.dtype))
    module = NeRFModule(renderer, functools.partial(torch.optim.Adam, lr=1e-3), lr_final=1e-4)
    directions = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1)
    batch = {"origins": -4 * directions, "directions": directions, "rgb": torch.rand(64, 3)}
    trainer = L.Trainer(accelerator="cpu", precision="bf16-mixed", max_steps=5, logger=False,
                        enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
                        limit_val_batches=0)
    trainer.fit(module, train_dataloaders=DataLoader([batch] * 5, batch_size=None))
    assert trainer.global_step == 5
    assert torch.bfloat16 in network_dtypes  # autocast was on for the network
    assert rendered_dtypes and set(rendered_dtypes) == {torch.float32}
    assert all(torch.isfinite(p).all() for p in module.parameters())
    # the bf16 render is the float32 render to bf16's precision (8 significant bits)
    with torch.no_grad():
        exact = renderer(batch["origins"], directions, deterministic=True)["fine"]
        with torch.autocast("cpu", dtype=torch.bfloat16):
            mixed = renderer(batch["origins"], directions, deterministic=True)["fine"]
    assert mixed["rgb"].dtype == torch.float32 and mixed["depth"].dtype == torch.float32
    torch.testing.assert_close(mixed["rgb"], exact["rgb"], atol=0.03, rtol=0)


def whole_image(size: int) -> dict:
    """An evaluation batch: one image of ``size`` x ``size`` rays (each towards the origin) and a random target."""
    rays = batch(size * size)
    return {"origins": rays["origins"].reshape(size, size, 3), "directions": rays["directions"].reshape(size, size, 3),
            "rgb": torch.rand(size, size, 3), "index": torch.tensor(0)}


def test_lpips_is_scored_once_built_and_kept_out_of_the_model(tmp_path, caplog, monkeypatch):
    from nerfexp.scoring.perceptual import LpipsScorer, lpips_network
    from tests.scoring.alexnet import alexnet_state, stand_in

    torch.manual_seed(0)
    torch.save(alexnet_state(), tmp_path / "alexnet.pth")
    stand_in(monkeypatch, tmp_path / "alexnet.pth")  # as the published weights
    plain = module(lambda: OpaqueField(0.5))
    m = module(lambda: OpaqueField(0.5))
    m.lpips_weights = str(tmp_path / "alexnet.pth")
    m.setup("fit")
    scorer = m.lpips_scorer
    m.setup("test")  # built once per process
    assert isinstance(scorer, LpipsScorer) and m.lpips_scorer is scorer
    assert m.state_dict().keys() == plain.state_dict().keys()  # not in checkpoints, not trained
    images = whole_image(32)
    scored = m._evaluate(images)
    expected = LpipsScorer(lpips_network(tmp_path / "alexnet.pth"))(scored["rgb"], images["rgb"])
    assert scored["lpips"] == expected > 0
    # images smaller than AlexNet takes: under auto one line, then no more scoring; under true an error
    with caplog.at_level("INFO"):
        assert math.isnan(m._evaluate(whole_image(16))["lpips"]) and math.isnan(m._evaluate(whole_image(32))["lpips"])
    lines = [r.getMessage() for r in caplog.records if "LPIPS" in r.getMessage()]
    assert lines == ["LPIPS not scored: LPIPS needs images of at least 31 x 31 pixels (AlexNet's strides and pools), "
                     "these are 16 x 16"]
    m.lpips, m.lpips_scorer = True, scorer
    with pytest.raises(ConfigError, match=r"^model.lpips=true: LPIPS needs images of at least 31 x 31 pixels"):
        m._evaluate(whole_image(16))


def test_without_lpips_an_image_is_scored_nan_there(monkeypatch, tmp_path):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))  # an empty hub cache: auto finds no weights
    m = module(lambda: OpaqueField(0.5))
    m.setup("test")
    assert m.lpips_scorer is None and math.isnan(m._evaluate(whole_image(32))["lpips"])
    off = module(lambda: OpaqueField(0.5))
    off.lpips = False
    off.setup("test")
    assert off.lpips_scorer is None


def test_training_values_are_logged_on_the_steps_the_logger_writes_and_only_there(tmp_path):
    # log_every_n_steps=3 over 7 steps: Lightning writes after the 3rd and the 6th batch (rows of steps 2 and 5,
    # counted from 0); a value logged on another step is never written, so the module logs none there
    class Batches(L.Callback):
        started = 0

        def on_train_batch_start(self, *args):
            self.started += 1

    m, batches, calls = module(ConstantField), Batches(), []
    log = m.log
    m.log = lambda name, *args, **kwargs: calls.append((name, batches.started)) or log(name, *args, **kwargs)
    trainer = L.Trainer(max_steps=7, accelerator="cpu", log_every_n_steps=3, logger=CSVLogger(tmp_path),
                        callbacks=[batches], enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False)
    trainer.fit(m, train_dataloaders=DataLoader([batch(8) for _ in range(7)], batch_size=None))
    with open(Path(trainer.logger.log_dir) / "metrics.csv") as file:
        rows = list(csv.DictReader(file))
    for name in ("train/loss", "train/rays_per_s"):  # in training_step and in on_train_batch_end
        assert [int(row["step"]) for row in rows if row.get(name)] == [2, 5], name
        assert [batch for logged, batch in calls if logged == name] == [3, 6], name


def test_own_weights_are_scored_and_recorded_as_lpips_custom_never_as_lpips(tmp_path):
    from nerfexp.scoring.perceptual import LpipsScorer, lpips_network
    from nerfexp.training.recorders import scores_record, scores_text
    from tests.scoring.alexnet import alexnet_state

    weights = tmp_path / "mine.pth"
    torch.save(alexnet_state(seed=3), weights)
    m = module(lambda: OpaqueField(0.5))
    m.lpips, m.lpips_weights, m.lpips_custom = True, str(weights), True
    m.setup("test")
    images = whole_image(32)
    scored = m._evaluate(images)
    expected = LpipsScorer(lpips_network(weights))(scored["rgb"], images["rgb"])
    assert scored["lpips_custom"] == expected > 0 and math.isnan(scored["lpips"])
    record = scores_record({0: scored})
    assert record["test_lpips_custom"] == expected and "test_lpips" not in record
    digest = hashlib.sha256(weights.read_bytes()).hexdigest()
    assert m.lpips_record(record) == {"lpips_weights_sha256": digest}
    assert m.lpips_record(scores_record({0: {"psnr": 20.0, "ssim": 0.5}})) == {}  # no LPIPS, no weights named
    text = scores_text({**record, "test_psnr": 20.0, "test_ssim": 0.5})
    assert text == f"test PSNR 20.00 dB, SSIM 0.5000, LPIPS with your own weights (not comparable) {expected:.4f}"
