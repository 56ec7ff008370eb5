"""The run directory: finding a run, reading the config of a run made before the package's layers,
metrics appended by several processes at once, and telling a run's process from a reused pid."""

import hashlib
import json
import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import tomllib
import torch
from hydra import compose, initialize_config_module
from hydra.utils import get_class, instantiate
from omegaconf import OmegaConf

from nerfexp import manifest
from nerfexp.commands import scene
from nerfexp.errors import ConfigError, NerfexpError
from nerfexp.nerf.hashgrid import HashGridEncoding
from nerfexp.nerf.proposal import ProposalSampler
from nerfexp.nerf.samplers import HierarchicalSampler
from nerfexp.rundir.claim import admit_run, claim, held_run, remove_entries
from nerfexp.rundir.layout import (
    LAST_CHECKPOINT,
    RUN_CONFIG,
    append_metrics,
    cpu_model,
    machine,
    process_alive,
    process_start,
    read_metrics,
)
from nerfexp.rundir.trained import MOVED_TARGETS, SHIMS_UNTIL, find_run, run_config
from nerfexp.settings.checks import check_run_settings
from tests.helpers import REPO, digests, one_error_line, run_nerfexp, tiny_config

PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())

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
    for path in ("model", "model.renderer", "model.renderer.field.position_encoding", "model.renderer.grid"):
        get_class(OmegaConf.select(cfg, path)._target_)  # importable where the class lives now
    model = instantiate(cfg.model)
    assert model.renderer.coarse.density_noise_std == 1.0 and model.renderer.grid is not None
    assert "callbacks" not in cfg  # only training builds them (nerfexp.rundir.saved_configs.TRAINING_ONLY)


@pytest.mark.parametrize(("scale", "sizes"), [("cpu", (16, 256)), ("paper", (19, 2048))])
def test_a_hash_grid_run_saved_with_its_sizes_in_the_scale_group_is_read_with_those_sizes(tmp_path, scale, sizes):
    # a run saved when scale.hash_log2_table_size and scale.hash_finest held the hash grid's sizes (the
    # encoding read them by interpolation), here with other values than either scale's own
    with initialize_config_module("nerfexp.conf", version_base=None):
        plain = OmegaConf.to_container(compose("config", overrides=["encoding=hashgrid", f"scale={scale}"]))
    assert (plain["encoding"]["position"]["log2_table_size"], plain["encoding"]["position"]["finest"]) == sizes
    plain["scale"] |= {"hash_log2_table_size": 12, "hash_finest": 64}
    plain["encoding"]["position"] |= {"log2_table_size": "${scale.hash_log2_table_size}",
                                      "finest": "${scale.hash_finest}"}
    (tmp_path / RUN_CONFIG).parent.mkdir()
    OmegaConf.save(OmegaConf.create(plain), tmp_path / RUN_CONFIG)
    cfg = run_config(tmp_path)
    check_run_settings(cfg)  # the run's own keys, which this version no longer has, are not refused
    encoding = instantiate(cfg.model.renderer.field.position_encoding)
    assert (encoding.table_size, encoding.resolutions[-1]) == (2 ** 12, 64)


HASH_GRID = "nerfexp.nerf.hashgrid.HashGridEncoding"


# where the hash grid's class lived: in nerfexp.nerf.encodings before it had a module of its own, and in
# nerfexp.encodings before the layers (whose prefix entry takes it to nerfexp.nerf.encodings, and on from there)
@pytest.mark.parametrize("old", ["nerfexp.nerf.encodings.HashGridEncoding", "nerfexp.encodings.HashGridEncoding"])
def test_a_hash_grid_run_saved_before_the_grid_had_its_own_module_is_built_with_the_current_class(
        tmp_path, monkeypatch, old):
    with initialize_config_module("nerfexp.conf", version_base=None):
        text = OmegaConf.to_yaml(compose("config", overrides=["encoding=hashgrid", "scale=cpu"]))
    assert text.count(f"_target_: {HASH_GRID}\n") == 1  # encoding.position; the field's is a reference to it
    (tmp_path / RUN_CONFIG).parent.mkdir()
    (tmp_path / RUN_CONFIG).write_text(text.replace(HASH_GRID, old))
    cfg = run_config(tmp_path)
    assert cfg.encoding.position._target_ == HASH_GRID
    encoding = instantiate(cfg.model.renderer.field.position_encoding)
    assert type(encoding) is HashGridEncoding and encoding.resolutions[-1] == cfg.encoding.position.finest
    # without the grid's own entry either old path names no class nerfexp builds
    monkeypatch.delitem(MOVED_TARGETS, "nerfexp.nerf.encodings.HashGridEncoding")
    with pytest.raises(ConfigError, match="HashGridEncoding' is not a class nerfexp builds"):
        run_config(tmp_path)


# The view-dependence axis's classes under the names they had as colour heads, each in the run config of its option
# (view_dependence=OPTION); the first also where it lived before the layers (nerfexp.fields): moved, then renamed
RENAMED_HEADS = [("mlp", "nerfexp.nerf.fields.ViewMLPHead"), ("mlp", "nerfexp.fields.ViewMLPHead"),
                 ("none", "nerfexp.nerf.fields.DiffuseHead"), ("sh", "nerfexp.nerf.fields.SphericalHarmonicsHead"),
                 ("ref", "nerfexp.nerf.reflection.ReflectionHead")]


@pytest.mark.parametrize(("option", "old"), RENAMED_HEADS, ids=[old for _, old in RENAMED_HEADS])
def test_a_run_saved_with_a_colour_heads_old_name_is_built_with_the_view_dependence_class(tmp_path, monkeypatch,
                                                                                           option, old):
    cfg = tiny_config(f"view_dependence={option}", "model.lpips=false")
    current = cfg.view_dependence._target_
    assert current.rpartition(".")[2].endswith("ViewDependence")  # the axis's name: conf/view_dependence/
    text = OmegaConf.to_yaml(cfg)
    assert text.count(f"_target_: {current}\n") == 1  # view_dependence; the field's is a reference to it
    (tmp_path / RUN_CONFIG).parent.mkdir()
    (tmp_path / RUN_CONFIG).write_text(text.replace(current, old))
    read = run_config(tmp_path)
    check_run_settings(read)
    assert read.view_dependence._target_ == current
    assert type(instantiate(read.model).renderer.coarse.view_head) is get_class(current)
    for name in [name for name in MOVED_TARGETS if name.endswith("Head")]:
        monkeypatch.delitem(MOVED_TARGETS, name)  # without the renames' entries the old name is no class nerfexp builds
    with pytest.raises(ConfigError, match=f"{old.rpartition('.')[2]}' is not a class nerfexp builds"):
        run_config(tmp_path)


def old_layout(cfg) -> str:
    """A composed config's text as nerfexp wrote it before the sampler group: the renderer held the sampler's
    settings (``nerfexp.rundir.trained.OLD_SAMPLER_KEYS``) and no ``sampler`` section existed."""
    plain = OmegaConf.to_container(cfg, resolve=False)
    del plain["sampler"], plain["model"]["renderer"]["sampler"]
    plain["model"]["renderer"].update(hierarchical="${hierarchical}", n_coarse="${scale.n_coarse}",
                                      n_fine="${scale.n_fine}", n_single="${scale.n_single}", proposal="${proposal}")
    return OmegaConf.to_yaml(OmegaConf.create(plain))


@pytest.mark.parametrize("hierarchical", [True, "proposal"])
def test_a_run_made_before_the_sampler_group_is_read_with_its_sampler_and_weights(tmp_path, hierarchical):
    cfg = tiny_config(f"hierarchical={hierarchical}", "model.lpips=false")
    (tmp_path / RUN_CONFIG).parent.mkdir()
    (tmp_path / RUN_CONFIG).write_text(old_layout(cfg))
    read = run_config(tmp_path)
    assert read.model.renderer.sampler.n_coarse == cfg.scale.n_coarse and "hierarchical" not in read.model.renderer
    torch.manual_seed(0)
    trained = instantiate(cfg.model)  # the weights a run made then saved, under the names it saved them
    old_names = {name.replace("renderer.sampler.", "renderer.proposal."): value
                 for name, value in trained.state_dict().items()}
    assert any(".proposal." in name for name in old_names) == (hierarchical == "proposal")
    module = instantiate(read.model)
    assert isinstance(module.renderer.sampler, {True: HierarchicalSampler, "proposal": ProposalSampler}[hierarchical])
    checkpoint = {"state_dict": dict(old_names)}
    module.on_load_checkpoint(checkpoint)  # as Lightning and nerfexp-eval before loading the weights
    module.load_state_dict(checkpoint["state_dict"])
    assert all(torch.equal(value, module.state_dict()[name]) for name, value in trained.state_dict().items())


def test_the_shims_for_runs_made_before_the_layers_go_by_the_version_they_name():
    version = tuple(int(part) for part in PYPROJECT["project"]["version"].split("."))
    assert version < SHIMS_UNTIL, ("nerfexp has reached the version that drops the shims of nerfexp.rundir.trained "
                                   "(MOVED_TARGETS, OLD_NOISE, OLD_SAMPLER_KEYS, MOVED_WEIGHTS): remove them, or "
                                   "name a later version")


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
from nerfexp.rundir.layout import append_metrics
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
    # whole, and no draft left beside it; recorded in the directory's manifest
    assert sorted(p.name for p in run_dir.iterdir()) == sorted(["status.json", *manifest.BOOKKEEPING])
    assert manifest.unproven(run_dir, ["status.json"]) == [] and manifest.read_records(run_dir).keys() == {
        "status.json"}
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
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == sorted(["status.json", *manifest.BOOKKEEPING])
    assert held_run(tmp_path / "run") == "a running run (seed=1)"


def a_failed_run(run_dir: Path, **status) -> Path:
    """A run directory as a run that failed on bad data leaves it: its status (``status``), config and log,
    recorded in its manifest."""
    (run_dir / ".hydra").mkdir(parents=True)
    (run_dir / ".hydra" / "config.yaml").write_text("seed: 0\n")
    (run_dir / "nerfexp.log").write_text("")
    record = {"state": "failed", "overrides": ["seed=0"], "host": socket.gethostname(), "pid": 1} | status
    (run_dir / "status.json").write_text(json.dumps(record))
    manifest.record(run_dir, [".hydra/config.yaml", "nerfexp.log", "status.json"])
    return run_dir


def test_a_run_into_a_blender_datasets_folder_is_one_line_and_changes_nothing(tmp_path):
    dataset = tmp_path / "lego"
    scene.main([str(dataset), "--resolution", "8", "--n-train", "2", "--n-val", "1", "--n-test", "2",
                "--supersample", "1"])
    (dataset / scene.MARKER).unlink()  # a dataset from elsewhere: the names nerfexp's test renders have
    before = digests(dataset)
    result = run_nerfexp("data=blender", f"data.root={dataset}", f"hydra.run.dir={dataset}", cwd=tmp_path)
    assert one_error_line(result) == (f"nerfexp: error: {dataset} holds files nerfexp did not make (test/r_0.png, "
                                      "test/r_1.png, train/r_0.png, ...): choose a new or empty directory "
                                      "(hydra.run.dir=...)")
    assert len(result.stderr.strip().splitlines()) == 1 and digests(dataset) == before


def test_a_sweep_into_a_folder_holding_other_files_is_one_line_and_changes_nothing(tmp_path):
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    (sweep / "notes.txt").write_text("mine")
    result = run_nerfexp("-m", "seed=0,1", f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert result.stderr.strip() == (f"nerfexp: error: {sweep} holds files this sweep did not make (notes.txt): "
                                     "choose a new or empty directory (hydra.sweep.dir=...)")
    assert result.returncode == 1 and digests(sweep) == {"notes.txt": hashlib.sha256(b"mine").hexdigest()}


def test_a_run_that_failed_on_bad_data_is_replaced_and_only_its_files_removed(tmp_path):
    run_dir = tmp_path / "run"
    bad = ["data=blender", f"data.root={tmp_path / 'missing'}", "logger=none", f"hydra.run.dir={run_dir}"]
    failed = run_nerfexp(*bad, cwd=tmp_path)
    assert "does not exist" in one_error_line(failed) and json.loads((run_dir / "status.json").read_text())[
        "state"] == "failed"
    (run_dir / "empty").mkdir()  # holds nothing: kept, and no reason to refuse
    again = run_nerfexp(*bad, "seed=7", cwd=tmp_path)
    notice, error = again.stderr.strip().splitlines()  # the advice never names a checkpoint that does not exist
    assert notice.startswith(f"nerfexp: {run_dir} holds a run that ended unfinished and saved no checkpoint: "
                             "replacing it, removing its 5 files (.hydra/config.yaml, ") and "resume=" not in error
    assert json.loads((run_dir / "status.json").read_text())["overrides"][-1] == "seed=7"
    assert (run_dir / "empty").is_dir()

    # a user's files put there since, of names a run's libraries and commands use: refused, nothing removed
    for name in ("report.md", "images/photo.png", "csv/mine.csv", "export/mesh.ply"):
        (run_dir / name).parent.mkdir(exist_ok=True)
        (run_dir / name).write_text("DO NOT LOSE")
    before = digests(run_dir)
    third = run_nerfexp(*bad, "seed=8", cwd=tmp_path)
    assert one_error_line(third) == (
        f"nerfexp: error: {run_dir / 'csv/mine.csv'}, {run_dir / 'export/mesh.ply'}, {run_dir / 'images/photo.png'} "
        f"and 1 more are not files nerfexp wrote (they are not in {run_dir / manifest.MANIFEST}, or changed since): "
        "move them elsewhere, or choose another directory (hydra.run.dir=...)")
    assert len(third.stderr.strip().splitlines()) == 1 and digests(run_dir) == before


def test_a_held_run_is_replaced_only_where_it_ended_unfinished_and_the_advice_names_a_saved_checkpoint(tmp_path):
    # failed, or running in a process of this host that no longer runs: replaced, all of it
    failed = a_failed_run(tmp_path / "failed")
    assert admit_run(failed, None) == [".hydra/config.yaml", "nerfexp.log", "status.json"]
    dead = subprocess.Popen([sys.executable, "-c", ""])
    dead.wait()
    killed = a_failed_run(tmp_path / "killed", state="running", pid=dead.pid, process_start=None)
    assert admit_run(killed, None) == [".hydra/config.yaml", "nerfexp.log", "status.json"]
    # running in this very process, or on another host: kept, and no checkpoint to resume from is named
    for state in ({"state": "running", "pid": os.getpid(), "process_start": process_start(os.getpid())},
                  {"state": "running", "host": "elsewhere"}, {"state": "finished"}):
        held = a_failed_run(tmp_path / str(len(list(tmp_path.iterdir()))), **state)
        with pytest.raises(NerfexpError, match=r"holds a \w+ run \(seed=0\): choose another directory") as error:
            admit_run(held, None)
        assert "resume=" not in str(error.value)
    # a failed run that saved a checkpoint is continued from the one it saved: never removed
    (failed / "checkpoints").mkdir()
    (failed / "checkpoints" / "epoch=0-step=30.ckpt").write_bytes(b"")
    with pytest.raises(NerfexpError, match=re.escape(f"resume={failed}/checkpoints/epoch=0-step=30.ckpt ")):
        admit_run(failed, None)
    (failed / LAST_CHECKPOINT).write_bytes(b"")
    with pytest.raises(NerfexpError, match=re.escape(f"resume={failed / LAST_CHECKPOINT} ")):
        admit_run(failed, None)
    assert admit_run(failed, str(failed / LAST_CHECKPOINT)) is None  # resume=: continued
    # a checkpoint laid in a folder that holds no run is not a run to continue
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "model.ckpt").write_bytes(b"")
    with pytest.raises(NerfexpError, match=r"holds files nerfexp did not make \(model.ckpt\)"):
        admit_run(elsewhere, str(elsewhere / "model.ckpt"))


def test_a_failed_runs_file_changed_since_nerfexp_wrote_it_is_kept_and_the_rest_removed_only_when_none_is(tmp_path):
    failed = a_failed_run(tmp_path / "failed")
    (failed / "nerfexp.log").write_text("a user's own log, in the name nerfexp gives its log")
    before = digests(failed)
    with pytest.raises(NerfexpError, match=re.escape(f"{failed / 'nerfexp.log'} is not a file nerfexp wrote")):
        admit_run(failed, None)
    assert digests(failed) == before
    (failed / "nerfexp.log").write_text("")  # as nerfexp wrote it: its own again
    entries = admit_run(failed, None)
    assert entries == [".hydra/config.yaml", "nerfexp.log", "status.json"]
    remove_entries(failed, entries)
    assert sorted(p.name for p in failed.iterdir()) == sorted(manifest.BOOKKEEPING)
    assert manifest.read_records(failed) == {} and admit_run(failed, None) == []  # a new or empty directory


def test_a_failed_run_of_an_earlier_nerfexp_or_with_a_damaged_manifest_is_refused_in_one_line(tmp_path):
    old = a_failed_run(tmp_path / "old")
    (old / manifest.MANIFEST).unlink()  # written before nerfexp kept a manifest
    before = digests(old)
    with pytest.raises(NerfexpError) as error:
        admit_run(old, None)
    assert str(error.value) == (
        f"{old} holds a failed run (seed=0) of an earlier nerfexp, which kept no record of the files it wrote (no "
        f"{manifest.MANIFEST}), so nothing in it is removed or written over: move its files elsewhere yourself, or "
        "choose another directory (hydra.run.dir=...)")
    (old / manifest.MANIFEST).write_text('{"files": [')
    with pytest.raises(NerfexpError, match=re.escape(f"{old / manifest.MANIFEST}: not JSON (") + ".*" + re.escape(
            f"), so nothing shows {old / '.hydra/config.yaml'}, {old / 'nerfexp.log'}, {old / 'status.json'} to be "
            "nerfexp's: move them elsewhere, or choose another directory (hydra.run.dir=...)")):
        admit_run(old, None)
    assert digests(old) == {**before, manifest.MANIFEST: hashlib.sha256(b'{"files": [').hexdigest()}


def test_a_resumed_run_writes_over_only_its_own_files(tmp_path):
    run_dir = a_failed_run(tmp_path / "run")
    (run_dir / LAST_CHECKPOINT).parent.mkdir()
    (run_dir / LAST_CHECKPOINT).write_bytes(b"weights")
    (run_dir / "notes.txt").write_text("mine")  # beside the run: a resumed run writes beside it
    assert admit_run(run_dir, str(run_dir / LAST_CHECKPOINT)) is None
    (run_dir / RUN_CONFIG).write_text("seed: 1  # changed by hand\n")  # Hydra would write over it
    with pytest.raises(NerfexpError, match=re.escape(
            f"{run_dir / RUN_CONFIG} is not a file nerfexp wrote (it is not in {run_dir / manifest.MANIFEST}, or "
            "changed since): move it elsewhere, or continue it in another directory "
            f"(resume={run_dir / LAST_CHECKPOINT} hydra.run.dir=...)")):
        admit_run(run_dir, str(run_dir / LAST_CHECKPOINT))


def test_the_machine_record_names_the_cpu_model_and_its_timing_units():
    """A run's machine line says which CPU measured its times (sessions get different CPUs) and the units
    that change them; a cpuinfo without flags or a model still gives a word."""
    amd = "processor : 0\nmodel name : AMD EPYC 9R14 96-Core\nflags : fpu sse avx2 avx512f avx512_bf16\n" \
          "processor : 1\nmodel name : other\nflags : fpu\n"
    assert cpu_model(amd) == "AMD EPYC 9R14 96-Core [avx2 avx512f avx512_bf16]"  # the first CPU's
    assert cpu_model("model name : Intel(R) Xeon(R) Processor\nflags : fpu sse2\n") == "Intel(R) Xeon(R) Processor"
    assert cpu_model("") == "CPU"
    if not Path("/proc/cpuinfo").exists() or torch.cuda.is_available():
        return
    device = machine()["device"]
    assert device.startswith(cpu_model(Path("/proc/cpuinfo").read_text()))
    assert f"({os.cpu_count()} cores" in device
