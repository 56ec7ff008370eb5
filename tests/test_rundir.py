"""The run directory: finding a run, reading the config of a run made before the package's layers,
metrics appended by several processes at once, and telling a run's process from a reused pid."""

import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hydra.utils import get_class, instantiate
from omegaconf import OmegaConf

from nerfexp.errors import NerfexpError
from nerfexp.rundir import (
    LAST_CHECKPOINT,
    RUN_CONFIG,
    append_metrics,
    claim,
    find_run,
    held_run,
    process_alive,
    process_start,
    read_metrics,
    run_config,
)

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


APPENDER = """
import sys, time
from pathlib import Path
from nerfexp.rundir import append_metrics
run_dir, writer, go = Path(sys.argv[1]), int(sys.argv[2]), Path(sys.argv[3])
while not go.exists():  # start together
    time.sleep(0.01)
for line in range(150):
    append_metrics(run_dir, {"writer": writer, "line": line, "padding": "x" * 200})
"""


def test_several_processes_appending_metrics_keep_every_line_whole(tmp_path):
    # 4 processes x 150 lines at once: read-then-replace kept about half; appends must keep all 600
    go = tmp_path / "go"
    writers = [subprocess.Popen([sys.executable, "-c", APPENDER, str(tmp_path), str(w), str(go)]) for w in range(4)]
    time.sleep(0.5)
    go.touch()
    assert all(w.wait(timeout=300) == 0 for w in writers)
    records = read_metrics(tmp_path)  # every line parses: none torn
    assert sorted((r["writer"], r["line"]) for r in records) == [(w, i) for w in range(4) for i in range(150)]
    for w in range(4):  # each writer's lines in its own order
        assert [r["line"] for r in records if r["writer"] == w] == list(range(150))


def test_a_line_still_being_written_is_not_read(tmp_path):
    append_metrics(tmp_path, {"step": 1})
    with open(tmp_path / "metrics.jsonl", "a") as file:
        file.write('{"step": 2, "ps')  # a writer's line, half there
    assert read_metrics(tmp_path) == [{"step": 1}]


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="process start times come from Linux's /proc")
def test_a_process_is_its_pid_and_its_start_and_a_reused_pid_is_another_process():
    started = process_start(os.getpid())
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        child_started = process_start(child.pid)
        assert isinstance(started, int) and child_started >= started  # clock ticks since boot: later
        assert process_alive(child.pid, child_started) and process_alive(child.pid, None)
        assert not process_alive(child.pid, child_started + 1)  # the pid, but not the process recorded
    finally:
        child.kill()
        child.wait()
    assert process_start(child.pid) is None and not process_alive(child.pid, child_started)


def test_a_directory_is_claimed_once_and_then_holds_a_run(tmp_path):
    run_dir = tmp_path / "run"
    assert held_run(run_dir) is None
    assert claim(run_dir, ["seed=1"]) and not claim(run_dir, ["seed=2"])  # the second run finds it taken
    assert held_run(run_dir) == "a running run (seed=1)"
    assert [p.name for p in run_dir.iterdir()] == ["status.json"]  # whole, and no draft left beside it
    status = json.loads((run_dir / "status.json").read_text())
    assert (status["pid"], status["process_start"]) == (os.getpid(), process_start(os.getpid()))
    results_only = tmp_path / "old"  # a run's results without a status (a run's files copied elsewhere)
    (results_only / "checkpoints").mkdir(parents=True)
    assert held_run(results_only) == "a run's results"


def test_a_run_directory_leads_to_the_checkpoint_its_test_scored(tmp_path):
    (tmp_path / RUN_CONFIG).parent.mkdir()
    (tmp_path / RUN_CONFIG).write_text(OLD_CONFIG)
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / LAST_CHECKPOINT).write_bytes(b"another run's weights")
    scored = tmp_path / "checkpoints" / "last-v1.ckpt"
    scored.write_bytes(b"the weights the test scored")
    digest = hashlib.sha256(b"the weights the test scored").hexdigest()
    (tmp_path / "results.json").write_text(json.dumps({"checkpoint": {"path": "checkpoints/last-v1.ckpt",
                                                                      "sha256": digest}}))
    assert find_run(tmp_path) == (tmp_path, scored)
    assert find_run(tmp_path / LAST_CHECKPOINT) == (tmp_path, tmp_path / LAST_CHECKPOINT)  # named: used as is
    scored.write_bytes(b"weights written over it since")
    with pytest.raises(NerfexpError, match="is not the checkpoint the run's test scored"):
        find_run(tmp_path)


def test_a_directory_is_claimed_once_where_the_file_system_has_no_hard_links(tmp_path, monkeypatch):
    def no_links(source, target):
        raise PermissionError(f"{target}: no hard links here")

    monkeypatch.setattr(os, "link", no_links)
    assert claim(tmp_path / "run", ["seed=1"]) and not claim(tmp_path / "run", ["seed=2"])
    assert [p.name for p in (tmp_path / "run").iterdir()] == ["status.json"]
    assert held_run(tmp_path / "run") == "a running run (seed=1)"
