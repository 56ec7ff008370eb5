"""The run directory: finding a run, and reading the config of a run made before the package's layers
(``nerfexp.rundir.run_config``)."""

import pytest
from hydra.utils import get_class, instantiate
from omegaconf import OmegaConf

from nerfexp.errors import NerfexpError
from nerfexp.rundir import LAST_CHECKPOINT, RUN_CONFIG, find_run, run_config

# The config an LLFF run saved before the layers (as nerfexp wrote it then, abridged to what builds
# objects): the old module paths of every class, and the field's noise read from the data group.
OLD_CONFIG = """
model:
  _target_: nerfexp.module.NeRFModule
  renderer:
    _target_: nerfexp.renderer.VolumeRenderer
    field:
      _target_: nerfexp.fields.NeRFField
      _partial_: true
      position_encoding:
        _target_: nerfexp.encodings.PositionalEncoding
        n_freqs: 4
      view_head:
        _target_: nerfexp.fields.ViewMLPHead
        _partial_: true
        direction_encoding:
          _target_: nerfexp.encodings.IdentityEncoding
        hidden: 8
      depth: 2
      width: 16
      skips: [1]
      density_noise_std: ${oc.select:data.density_noise_std,0.0}
    hierarchical: true
    n_coarse: 4
    n_fine: 4
    n_single: 8
    near: ${data.near}
    far: ${data.far}
    background: ${data.background}
    grid:
      _target_: nerfexp.occupancy.OccupancyGrid
  optimizer:
    _target_: torch.optim.Adam
    _partial_: true
    lr: 0.001
  lr_final: 0.0001
data:
  _target_: nerfexp.data.llff.LLFFScene
  root: /somewhere
  near: 0.0
  far: 1.0
  background: black
  density_noise_std: 1.0
callbacks:
  flush_denormals:
    _target_: nerfexp.module.FlushDenormals
  guard:
    _target_: nerfexp.guards.TrainingGuard
"""


def test_a_run_made_before_the_layers_is_read_with_the_current_classes(tmp_path):
    (tmp_path / RUN_CONFIG).parent.mkdir()
    (tmp_path / RUN_CONFIG).write_text(OLD_CONFIG)
    cfg = run_config(tmp_path, ["data.root=/moved"])
    assert "density_noise_std" not in cfg.data and cfg.data.root == "/moved"
    for path in ("model", "model.renderer", "model.renderer.field.position_encoding", "model.renderer.grid",
                 "callbacks.flush_denormals", "callbacks.guard"):
        get_class(OmegaConf.select(cfg, path)._target_)  # importable where the class lives now
    model = instantiate(cfg.model)
    assert model.renderer.coarse.density_noise_std == 1.0 and model.renderer.grid is not None
    assert type(instantiate(cfg.callbacks.flush_denormals)).__module__ == "nerfexp.training.callbacks"


def test_a_run_is_found_by_its_directory_or_a_checkpoint_in_it(tmp_path):
    (tmp_path / RUN_CONFIG).parent.mkdir()
    (tmp_path / RUN_CONFIG).write_text(OLD_CONFIG)
    with pytest.raises(NerfexpError, match="has saved no checkpoint"):
        find_run(tmp_path)
    (tmp_path / LAST_CHECKPOINT).parent.mkdir()
    (tmp_path / LAST_CHECKPOINT).write_bytes(b"")
    assert find_run(tmp_path) == find_run(tmp_path / LAST_CHECKPOINT) == (tmp_path, tmp_path / LAST_CHECKPOINT)
    with pytest.raises(NerfexpError, match="is not a run directory"):
        find_run(tmp_path / "checkpoints")
