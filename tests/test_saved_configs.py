"""Run directories and checkpoints from others are read as data: a crafted config or checkpoint is an
error before anything is built or unpickled, and its payload never runs."""

import shutil
from pathlib import Path

import pytest
import torch
import yaml
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from nerfexp.errors import ConfigError
from nerfexp.rundir import run_config
from nerfexp.saved_configs import buildable, targets
from tests.helpers import run_nerfexp


class Payload:
    """Unpickled, it creates the file ``marker`` (as a crafted pickle could run anything)."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return open, (str(self.marker), "w")


@pytest.mark.parametrize("overrides", [[], ["logger=csv", "acceleration=occupancy", "trainer=ddp"],
                                       ["logger=mlflow", "view_dependence=sh", "encoding=none"],
                                       ["logger=wandb", "data=blender", "data.root=/x", "view_dependence=none"]])
def test_every_target_of_nerfexps_own_configs_may_be_built_from_a_saved_one(overrides):
    with initialize_config_module("nerfexp.conf", version_base=None):
        cfg = compose("config", overrides=overrides)
    found = list(targets(OmegaConf.to_container(cfg, resolve=False)))
    assert len(found) >= 8
    assert [(key, target) for key, target in found if not buildable(target)] == []


@pytest.mark.parametrize("target", [
    "torch.load", "os.system", "builtins.eval", "subprocess.Popen",
    "nerfexp.rundir.torch.load",  # a function reached through a nerfexp module
    "nerfexp.rundir.Path",  # a class a nerfexp module imported, not nerfexp's
    "nerfexp.files.atomic_write",  # nerfexp's, but a function that writes files
    "torch.optim.adam.torch.nn.Module",  # reached from torch.optim, not an optimizer
    "lightning.pytorch.loggers.tensorboard.os.system",
    "nerfexp.no_such_module.Thing", "${oc.env:HOME}", 42, None])
def test_anything_else_may_not(target):
    assert not buildable(target)


@pytest.fixture
def crafted(tiny_run, tmp_path) -> tuple[Path, Path]:
    """A copy of a finished run whose saved config builds ``torch.load`` of a crafted pickle
    (``weights_only: false``) where the positional encoding should be; and the payload's marker file."""
    run_dir, marker = tmp_path / "shared_run", tmp_path / "payload_ran"
    shutil.copytree(tiny_run, run_dir)
    torch.save({"weights": Payload(marker)}, tmp_path / "crafted.pt")
    config_path = run_dir / ".hydra" / "config.yaml"
    config = yaml.safe_load(config_path.read_text())
    config["model"]["renderer"]["field"]["position_encoding"] = {
        "_target_": "torch.load", "f": str(tmp_path / "crafted.pt"), "weights_only": False}
    config_path.write_text(yaml.safe_dump(config))
    return run_dir, marker


@pytest.mark.slow
@pytest.mark.parametrize("script", ["nerfexp-eval", "nerfexp-render"])
def test_a_crafted_run_config_is_refused_before_anything_is_built(crafted, tmp_path, script):
    run_dir, marker = crafted
    before = sorted(p.name for p in run_dir.iterdir())
    result = run_nerfexp(str(run_dir), cwd=tmp_path, script=script)
    assert result.returncode != 0 and "Traceback" not in result.stderr, result.stderr[-3000:]
    (line,) = [line for line in result.stderr.splitlines() if line.startswith(f"{script}: error:")]
    assert f"{run_dir / '.hydra' / 'config.yaml'}: model.renderer.field.position_encoding._target_='torch.load'" in line
    assert "read as data, never run" in line
    assert not marker.exists() and sorted(p.name for p in run_dir.iterdir()) == before


@pytest.mark.slow
def test_a_crafted_checkpoint_is_refused_by_resume_eval_and_render(tiny_run, tmp_path, tiny):
    marker = tmp_path / "payload_ran"
    run_dir = tmp_path / "shared_run"
    shutil.copytree(tiny_run, run_dir)
    checkpoint = run_dir / "checkpoints" / "last.ckpt"
    state = torch.load(checkpoint, weights_only=True)
    state["payload"] = Payload(marker)  # a real checkpoint with one object that runs code when unpickled
    torch.save(state, checkpoint)
    for script, args in (("nerfexp-eval", [str(checkpoint)]), ("nerfexp-render", [str(checkpoint)]),
                         ("nerfexp", [*tiny, f"resume={checkpoint}", f"hydra.run.dir={tmp_path / 'resumed'}"])):
        result = run_nerfexp(*args, cwd=tmp_path, script=script)
        assert result.returncode != 0 and "Traceback" not in result.stderr, (script, result.stderr[-3000:])
        (line,) = [line for line in result.stderr.splitlines() if line.startswith(f"{script}: error:")]
        assert f"{checkpoint}: not a checkpoint nerfexp can read as data (UnpicklingError: Weights only load failed" \
               in line, (script, line)
        assert not marker.exists()
    assert not (tmp_path / "resumed" / "metrics.jsonl").exists()


@pytest.mark.parametrize("text", ["- a list\n- not a mapping\n", "model: {renderer: [unclosed\n", "\xff\xfe"])
def test_a_saved_config_that_is_not_one_is_an_error_naming_the_file(tmp_path, text):
    (tmp_path / ".hydra").mkdir()
    (tmp_path / ".hydra" / "config.yaml").write_bytes(text.encode("latin-1"))
    with pytest.raises(ConfigError, match=f"{tmp_path / '.hydra' / 'config.yaml'}: not a config nerfexp can read"):
        run_config(tmp_path)
