"""The real config composes and builds every combination of components, at both scales."""

import inspect
import subprocess
import sys

import lightning as L
import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.utils import get_class, instantiate
from omegaconf import OmegaConf

from nerfexp.nerf.bounds import Bounded
from nerfexp.nerf.encodings import IdentityEncoding, PositionalEncoding
from nerfexp.nerf.fields import MLPViewDependence, NoViewDependence, SphericalHarmonicsViewDependence
from nerfexp.nerf.hashgrid import HashGridEncoding
from nerfexp.nerf.proposal import ProposalSampler
from nerfexp.nerf.reflection import ReflectionViewDependence


def build(*overrides):
    with initialize_config_module("nerfexp.conf", version_base=None):
        cfg = compose("config", overrides=list(overrides))
    return cfg, instantiate(cfg.model)


@pytest.mark.parametrize("encoding", ["none", "posenc", "hashgrid"])
@pytest.mark.parametrize("view", ["mlp", "none", "sh", "ref"])
@pytest.mark.parametrize("hierarchical", [True, False, "proposal"])
def test_every_combination_builds_and_renders(encoding, view, hierarchical):
    cfg, model = build(f"encoding={encoding}", f"view_dependence={view}", f"hierarchical={hierarchical}")
    renderer = model.renderer
    assert (renderer.fine is not None) == (hierarchical is True)
    assert isinstance(renderer.sampler, ProposalSampler) == (hierarchical == "proposal")
    if hierarchical == "proposal":  # one density network per round, each its own copy of the encoding axis's
        networks = renderer.sampler.networks
        kinds = {type(net.position_encoding) for net in networks}
        assert len(networks) == 2 and kinds == {type(renderer.coarse.position_encoding)}
        assert networks[0].trunk[0].weight is not networks[1].trunk[0].weight
    field = renderer.coarse
    kind = {"none": IdentityEncoding, "posenc": PositionalEncoding, "hashgrid": HashGridEncoding}[encoding]
    assert isinstance(field.position_encoding, kind)
    for bounded in (m for m in renderer.modules() if isinstance(m, Bounded)):
        bounded.set_bounds(torch.tensor([[-1.5] * 3, [1.5] * 3]))  # what training does from the scene
    head = {"mlp": MLPViewDependence, "none": NoViewDependence, "sh": SphericalHarmonicsViewDependence,
            "ref": ReflectionViewDependence}[view]
    assert isinstance(field.view_head, head)
    if hierarchical is True:  # separate networks, not one shared
        assert field is not renderer.fine and field.trunk[0].weight is not renderer.fine.trunk[0].weight
    directions = torch.nn.functional.normalize(torch.randn(4, 3), dim=-1)
    out = renderer(-4 * directions, directions, deterministic=True)
    final = out["fine" if hierarchical is True else "coarse"]
    assert torch.isfinite(final["rgb"]).all()
    # the regularizers each choice adds, finite and trainable (Ref-NeRF's normals through a hash grid too)
    names = ({"interlevel"} if hierarchical == "proposal" else set()) | ({"normals", "orientation"} if view == "ref"
                                                                          else set())
    assert set(final.get("regularizers", {})) == names
    if names:
        sum(final["regularizers"].values()).backward()
        assert all(torch.isfinite(p.grad).all() for p in renderer.parameters() if p.grad is not None)


def test_hashgrid_has_instant_ngps_field_and_optimizer_and_no_decay_on_its_tables():
    cfg, model = build("encoding=hashgrid")
    enc = model.renderer.coarse.position_encoding
    assert (len(enc.resolutions), enc.features_per_level, enc.table_size) == (16, 2, 2**16)
    assert enc.resolutions[0] == 16 and enc.resolutions[-1] == cfg.encoding.position.finest == 256
    assert len(model.renderer.coarse.trunk) == 1 and model.renderer.coarse.trunk[0].out_features == 64
    model.trainer = L.Trainer(max_steps=10, logger=False, enable_checkpointing=False, enable_progress_bar=False)
    optimizer = model.configure_optimizers()["optimizer"]
    assert optimizer.defaults["eps"] == 1e-15 and optimizer.defaults["betas"] == (0.9, 0.99)
    networks, tables = optimizer.param_groups
    assert networks["weight_decay"] == 1e-6 and tables["weight_decay"] == 0
    table_ids = {id(p) for net in (model.renderer.coarse, model.renderer.fine)
                 for p in net.position_encoding.parameters()}
    assert {id(p) for p in tables["params"]} == table_ids
    assert len(networks["params"]) + len(tables["params"]) == len(list(model.parameters()))
    _, paper = build("encoding=hashgrid", "scale=paper")  # Instant-NGP's sizes for the Blender scenes
    enc = paper.renderer.coarse.position_encoding
    assert (enc.table_size, enc.resolutions[-1]) == (2**19, 2048)


@pytest.mark.parametrize(("scale", "log2_table_size", "finest"), [("cpu", 16, 256), ("paper", 19, 2048)])
def test_the_hash_grids_sizes_follow_the_scale_and_the_command_line_wins(scale, log2_table_size, finest):
    # the encoding as it was built when the scale group held these sizes (scale.hash_log2_table_size, hash_finest)
    expected = {"_target_": "nerfexp.nerf.hashgrid.HashGridEncoding", "n_levels": 16, "features_per_level": 2,
                "log2_table_size": log2_table_size, "coarsest": 16, "finest": finest, "include_input": False,
                "sparse_gradients": False}
    for order in ([f"scale={scale}", "encoding=hashgrid"], ["encoding=hashgrid", f"scale={scale}"],
                  ["experiment=fast", f"scale={scale}"]):
        cfg, _ = build(*order)
        assert OmegaConf.to_container(cfg.model.renderer.field.position_encoding, resolve=True) == expected
        assert not any(key.startswith("hash_") for key in cfg.scale)  # one owner: the encoding's config
    cfg, model = build("encoding=hashgrid", f"scale={scale}", "encoding.position.log2_table_size=12",
                       "encoding.position.finest=64")
    enc = model.renderer.coarse.position_encoding
    assert (enc.table_size, enc.resolutions[-1]) == (2 ** 12, 64)


def test_the_fast_preset_is_one_hash_grid_network_with_the_occupancy_grid_in_float32_and_the_command_line_wins():
    cfg, model = build("experiment=fast")
    assert isinstance(model.renderer.coarse.position_encoding, HashGridEncoding)
    assert model.renderer.grid is not None and model.renderer.fine is None  # one network: the grid skips for it
    assert model.renderer.sampler.field_names == ("coarse",) and cfg.hierarchical is False
    assert len(model.renderer.coarse.trunk) == 1  # the hash grid's own field (field=ngp)
    assert cfg.trainer.precision == "32-true" and cfg.scale.steps == cfg.trainer.max_steps == 5000
    _, default = build()
    assert isinstance(default.renderer.coarse.position_encoding, PositionalEncoding) and default.renderer.grid is None
    cfg, model = build("experiment=fast", "encoding=posenc", "scale.steps=50", "trainer.precision=auto")
    assert isinstance(model.renderer.coarse.position_encoding, PositionalEncoding)  # any setting after it wins
    assert model.renderer.grid is not None and (cfg.scale.steps, cfg.trainer.precision) == (50, "auto")


def test_paper_scale_is_the_papers_network():
    cfg, model = build("scale=paper")
    r = model.renderer
    assert (r.sampler.n_coarse, r.sampler.n_fine, r.evaluations_per_ray) == (64, 128, 64 + 192)
    assert cfg.datamodule.batch_rays == 4096 and cfg.model.optimizer.lr == 5e-4 and cfg.model.lr_final == 5e-5
    assert cfg.encoding.position.n_freqs == 10 and cfg.encoding.direction.n_freqs == 4
    # 8 x 256 with the skip into the sixth layer, a 128-wide view layer: 595,844 parameters per network.
    trunk = (63 * 256 + 256) + 4 * (256 * 256 + 256) + ((256 + 63) * 256 + 256) + 2 * (256 * 256 + 256)
    head = (256 * 256 + 256) + ((256 + 27) * 128 + 128) + (128 * 3 + 3)
    assert sum(p.numel() for p in r.coarse.parameters()) == trunk + 257 + head == 595_844
    _, flat = build("scale=paper", "hierarchical=false")
    assert flat.renderer.evaluations_per_ray == 256 and flat.renderer.fine is None


def test_plain_install_finds_its_configs(tmp_path):
    """``pip install .`` (not editable) must carry conf/ inside the package."""
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps",
                    "--target", str(target), "."], check=True, cwd=__file__.rsplit("/tests/", 1)[0])
    probe = ("import nerfexp, sys; from hydra import compose, initialize_config_module\n"
             "with initialize_config_module('nerfexp.conf', version_base=None):\n"
             "    cfg = compose('config', overrides=['data=blender', 'scale=paper'])\n"
             "print(nerfexp.__file__, cfg.data._target_, cfg.scale.width)")
    out = subprocess.run([sys.executable, "-c", probe], cwd=tmp_path, env={"PYTHONPATH": str(target)},
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert str(target) in out.stdout and "nerfexp.data.blender.BlenderScene 256" in out.stdout


def targets(node, path="cfg"):
    """Every ``(path, config)`` in ``node`` that builds an object (has ``_target_``)."""
    if isinstance(node, dict):
        if "_target_" in node:
            yield path, node
        for key, value in node.items():
            yield from targets(value, f"{path}.{key}")


@pytest.mark.parametrize("overrides", [[], ["data=blender", "data.root=/x", "scale=paper", "logger=csv"],
                                       ["data=llff", "data.root=/x", "acceleration=occupancy", "logger=mlflow",
                                        "encoding=hashgrid"],
                                       ["data=colmap", "data.root=/x", "view_dependence=sh", "trainer=ddp",
                                        "logger=wandb"]])
def test_every_key_of_a_config_is_an_argument_of_the_class_it_builds(overrides):
    # configs mirror what they build: a key that no argument takes is a typo or a setting nothing reads
    with initialize_config_module("nerfexp.conf", version_base=None):
        cfg = compose("config", overrides=overrides)
    built = list(targets(OmegaConf.to_container(cfg, resolve=False)))
    assert {path for path, _ in built} >= {"cfg.model", "cfg.model.renderer", "cfg.data", "cfg.datamodule",
                                           "cfg.trainer", "cfg.logger", "cfg.callbacks.checkpoint",
                                           "cfg.callbacks.flush_denormals", "cfg.callbacks.guard"}
    for path, node in built:
        parameters = inspect.signature(get_class(node["_target_"])).parameters
        if any(p.kind == p.VAR_KEYWORD for p in parameters.values()):
            continue
        keys = {key for key in node if not (key.startswith("_") and key.endswith("_"))}
        assert keys <= set(parameters), f"{path} ({node['_target_']}): {sorted(keys - set(parameters))}"


def test_the_fields_training_noise_is_the_scene_formats_and_llffs_is_the_papers():
    cfg, model = build()
    assert cfg.model.renderer.field.density_noise_std == 0 and model.renderer.coarse.density_noise_std == 0
    cfg, model = build("data=llff", "data.root=/x")
    assert cfg.data.density_noise_std == 1.0 and model.renderer.fine.density_noise_std == 1.0
    for override in ("data.density_noise_std=0.5", "model.renderer.field.density_noise_std=0.5"):
        cfg, model = build("data=llff", "data.root=/x", override)
        assert model.renderer.coarse.density_noise_std == model.renderer.fine.density_noise_std == 0.5
