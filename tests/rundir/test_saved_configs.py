"""Run directories and checkpoints from others are read as data: a crafted config or checkpoint is an
error before anything is built or unpickled, and its payload never runs."""

import shutil
from pathlib import Path

import pytest
import torch
import yaml
from hydra import compose, initialize_config_module
from hypothesis import given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf

from nerfexp.commands import evaluate, export, render, view
from nerfexp.errors import ConfigError
from nerfexp.rundir.layout import planned_jobs
from nerfexp.rundir.saved_configs import buildable, check_targets, named_targets, targets
from nerfexp.rundir.trained import run_config
from tests.helpers import TINY, one_error_line, run_nerfexp


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
    "nerfexp.rundir.trained.torch.load",  # a function reached through a nerfexp module
    "nerfexp.rundir.trained.Path",  # a class a nerfexp module imported, not nerfexp's
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
        assert f"{checkpoint}: not a checkpoint (it holds objects other than tensors" in line, (script, line)
        assert "weights_only" not in result.stderr, (script, line)  # never torch's advice to load it as code
        assert not marker.exists()
    assert not (tmp_path / "resumed" / "metrics.jsonl").exists()


# a "billion laughs": nine aliases of nine aliases ... of nine values, 9^9 values from 22 lines
LAUGHS = "a: &a [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n" + "".join(
    f"{b}: &{b} [{', '.join(['*' + a] * 9)}]\n" for a, b in zip("abcdefghijklmnopqrstu", "bcdefghijklmnopqrstuv"))


@pytest.mark.parametrize(("text", "reason"), [
    ("- a list\n- not a mapping\n", "a mapping of keys was expected"),
    ("model: {renderer: [unclosed\n", "not YAML (while parsing a flow sequence"),
    ("\xff\xfe", "not UTF-8 text"),
    (LAUGHS, "line 1: a YAML anchor or alias, which nerfexp does not read"),
    ("a: " + "[" * 10_000 + "]" * 10_000, "containers nested deeper than 64 levels"),
    ("a: " + "x" * (2 << 20), "larger than the 1,048,576 bytes nerfexp reads of such a file"),
])
def test_a_saved_config_that_is_not_one_is_an_error_naming_the_file(tmp_path, text, reason):
    (tmp_path / ".hydra").mkdir()
    (tmp_path / ".hydra" / "config.yaml").write_bytes(text.encode("latin-1"))
    with pytest.raises(ConfigError) as raised:
        run_config(tmp_path)  # at once: nothing is expanded
    assert str(raised.value).startswith(f"{tmp_path / '.hydra' / 'config.yaml'}: not a config nerfexp can read (")
    assert reason in str(raised.value)


# Interpolations: a saved config may only refer to its own keys; every resolver is refused wherever it is.

RESOLVERS = {  # a call of each resolver OmegaConf and Hydra register, and of one the test registers
    "oc.create": "${oc.create:{_target_: torch.load, f: payload.pt, weights_only: false}}",
    "oc.decode": "${oc.decode:'{a: 1}'}",
    "oc.env": "${oc.env:NERFEXP_TEST_SECRET}",
    "oc.select": "${oc.select:scale.width,1}",
    "oc.dict.keys": "${oc.dict.keys:scale}",
    "oc.dict.values": "${oc.dict.values:scale}",
    "oc.deprecated": "${oc.deprecated:scale.width}",
    "now": "${now:%Y}",
    "hydra": "${hydra:runtime.output_dir}",
    "nerfexp_test_payload": "${nerfexp_test_payload:x}",
}
POSITIONS = {  # where in a saved config: the value there, given the resolver's call
    "top level": ("seed", "{}"),
    "nested dict": ("model.renderer.field.width", "{}"),
    "list": ("scale.skips.0", "{}"),
    "deeper list": ("model.optimizer.betas.1", "{}"),
    "a _target_": ("encoding.position._target_", "{}"),
    "inside a string": ("data.background", "white{}"),
    "inside a reference's key": ("sampler.n_fine", "${{scale.{}}}"),
    "inside a resolver's argument": ("model.chunk", "${{oc.select:scale.chunk,{}}}"),
}


@pytest.fixture(scope="module")
def saved_text() -> str:
    """A saved config as a TINY run's ``.hydra/config.yaml`` holds it (composed, nothing resolved)."""
    with initialize_config_module("nerfexp.conf", version_base=None):
        return OmegaConf.to_yaml(compose("config", overrides=list(TINY)))


def put(config: dict, dotted: str, value) -> None:
    """Set the value at ``dotted`` (list items by index) in the plain containers ``config``."""
    *parents, leaf = dotted.split(".")
    for key in parents:
        config = config[int(key)] if isinstance(config, list) else config[key]
    config[int(leaf) if isinstance(config, list) else leaf] = value


def saved_run(tmp_path: Path, text: str, **values) -> Path:
    """A run directory (only its saved config) whose config is ``text`` with ``values`` at dotted keys
    (``__`` for ``.``)."""
    config = yaml.safe_load(text)
    for dotted, value in values.items():
        put(config, dotted.replace("__", "."), value)
    (tmp_path / ".hydra").mkdir(exist_ok=True)
    (tmp_path / ".hydra" / "config.yaml").write_text(yaml.safe_dump(config))
    return tmp_path


@pytest.fixture
def payload_resolver():
    """The resolver ``nerfexp_test_payload``, registered for the test; the arguments of its calls."""
    calls = []
    OmegaConf.register_new_resolver("nerfexp_test_payload", lambda *args: calls.append(args) or 1)
    yield calls
    OmegaConf.clear_resolver("nerfexp_test_payload")


@pytest.mark.parametrize("position", POSITIONS)
@pytest.mark.parametrize("resolver", RESOLVERS)
def test_every_resolver_is_refused_wherever_it_is(tmp_path, saved_text, payload_resolver, monkeypatch,
                                                  resolver, position):
    monkeypatch.setenv("NERFEXP_TEST_SECRET", "the reader's secret")
    key, form = POSITIONS[position]
    value = form.format(RESOLVERS[resolver])
    run_dir = saved_run(tmp_path, saved_text, **{key.replace(".", "__"): value})
    with pytest.raises(ConfigError) as raised:
        run_config(run_dir)
    first = "oc.select" if position == "inside a resolver's argument" else resolver
    assert str(raised.value) == (
        f"{run_dir / '.hydra' / 'config.yaml'}: {key}={value!r} uses the resolver {first}: a run directory from "
        "elsewhere is read as data: only plain references ${key} to its own keys are followed")
    assert payload_resolver == [] and "the reader's secret" not in str(raised.value)


def test_plain_references_are_followed(tmp_path, saved_text):
    run_dir = saved_run(tmp_path, saved_text, sampler__n_fine="${.n_coarse}",
                        model__chunk="${..scale.${which}}", which="chunk")
    cfg = run_config(run_dir)
    assert cfg.model.renderer.sampler.n_fine == cfg.scale.n_coarse == 16  # TINY's scale.n_coarse=16
    assert cfg.model.chunk == cfg.scale.chunk


# Escaped interpolations: resolving a config once turns ``\${x}`` into a live ``${x}``, which Hydra's instantiate
# resolves again (it resolves in place, then reads): text from a file must never get there.
ESCAPES = {  # how a resolver's call is written so that one resolution leaves a live one, or calls it
    "escaped once": "\\{}",  # \${...}: text ${...} after one resolution
    "escaped twice": "\\\\\\{}",  # \\\${...}: an escaped backslash, then an escaped interpolation
    "escaped backslash": "\\\\{}",  # \\${...}: an escaped backslash before a live interpolation
}
ESCAPED_POSITIONS = {"a value": "data.background", "a list item": "scale.skips.0", "a nested list item":
                     "model.optimizer.betas.1"}


@pytest.mark.parametrize("escape", ESCAPES)
@pytest.mark.parametrize("position", ESCAPED_POSITIONS)
@pytest.mark.parametrize("resolver", RESOLVERS)
def test_every_resolver_escaped_is_refused_wherever_it_is(tmp_path, saved_text, payload_resolver, monkeypatch,
                                                          resolver, position, escape):
    monkeypatch.setenv("NERFEXP_TEST_SECRET", "the reader's secret")
    key, value = ESCAPED_POSITIONS[position], ESCAPES[escape].format(RESOLVERS[resolver])
    run_dir = saved_run(tmp_path, saved_text, **{key.replace(".", "__"): value})
    with pytest.raises(ConfigError) as raised:
        run_config(run_dir)
    reason = (f"uses the resolver {resolver}" if escape == "escaped backslash" else
              "holds an escaped interpolation, text that becomes a live one when the run's objects are built")
    assert str(raised.value).startswith(f"{run_dir / '.hydra' / 'config.yaml'}: {key}={value!r} {reason}: ")
    assert payload_resolver == [] and "the reader's secret" not in str(raised.value)


@pytest.mark.parametrize("escape", ["", *ESCAPES])
@pytest.mark.parametrize("resolver", ["oc.create", "oc.env", "nerfexp_test_payload"])
def test_a_key_holding_an_interpolation_is_refused(tmp_path, saved_text, payload_resolver, resolver, escape):
    key = ESCAPES[escape].format(RESOLVERS[resolver]) if escape else RESOLVERS[resolver]
    config = yaml.safe_load(saved_text)
    config["model"]["renderer"][key] = 1
    run_dir = saved_run(tmp_path, yaml.safe_dump(config))
    with pytest.raises(ConfigError) as raised:
        run_config(run_dir)
    assert str(raised.value) == (f"{run_dir / '.hydra' / 'config.yaml'}: the key {'model.renderer.' + key!r} holds "
                                 "'${': a run directory from elsewhere is read as data: its keys are names, never "
                                 "interpolations")
    assert payload_resolver == []


def test_what_resolves_to_an_interpolation_never_reaches_what_is_built(tmp_path, saved_text, monkeypatch):
    # whatever way text could become ${...} after the check (here the reader's own override, which is not
    # checked as the file is), the resolved config holds none
    monkeypatch.setenv("NERFEXP_TEST_SECRET", "the reader's secret")
    run_dir = saved_run(tmp_path, saved_text)
    with pytest.raises(ConfigError) as raised:
        run_config(run_dir, ["data.background=\\${oc.env:NERFEXP_TEST_SECRET}"])
    assert str(raised.value) == (
        f"{run_dir / '.hydra' / 'config.yaml'}: data.background, resolved, is '${{oc.env:NERFEXP_TEST_SECRET}}': text "
        "with '${' in it, which building the run's objects would resolve again: a run directory from elsewhere is "
        "read as data, never resolved twice")


@pytest.mark.parametrize("overrides", [[], ["logger=csv", "trainer=ddp"], ["logger=mlflow"], ["logger=wandb"]])
def test_nerfexps_own_saved_configs_read_back_without_what_only_training_builds(tmp_path, overrides):
    with initialize_config_module("nerfexp.conf", version_base=None):
        text = OmegaConf.to_yaml(compose("config", overrides=[*TINY, *overrides]))
    assert "${hydra:runtime.output_dir}" in text
    cfg = run_config(saved_run(tmp_path, text))
    assert "callbacks" not in cfg and "logger" not in cfg and "default_root_dir" not in cfg.trainer
    assert "${" not in OmegaConf.to_yaml(OmegaConf.to_container(cfg, resolve=True))


def test_what_only_training_builds_is_never_read(tmp_path, saved_text, monkeypatch):
    # a resolver there would be refused anywhere else; here nothing reads it
    monkeypatch.setenv("NERFEXP_TEST_SECRET", "the reader's secret")
    run_dir = saved_run(tmp_path, saved_text, logger__save_dir="${oc.env:NERFEXP_TEST_SECRET}",
                        callbacks__guard__dirpath=RESOLVERS["oc.create"],
                        trainer__default_root_dir="${oc.env:NERFEXP_TEST_SECRET}")
    assert "the reader's secret" not in OmegaConf.to_yaml(OmegaConf.to_container(run_config(run_dir), resolve=True))


def test_a_reference_the_config_cannot_follow_is_an_error_naming_the_key(tmp_path, saved_text):
    run_dir = saved_run(tmp_path, saved_text, sampler__n_fine="${callbacks.checkpoint.every_n_train_steps}")
    with pytest.raises(ConfigError, match=f"^{run_dir / '.hydra' / 'config.yaml'}: cannot resolve the config at "
                                          r"sampler\.n_fine: Interpolation key 'callbacks\.checkpoint"):
        run_config(run_dir)


@pytest.mark.parametrize(("data_noise", "expected"), [(None, 0.0), (1.0, 1.0)])
def test_a_run_of_a_version_whose_field_selected_the_datas_noise_reads_back(tmp_path, saved_text, data_noise,
                                                                              expected):
    text = saved_text.replace("density_noise_std: 0.0", "density_noise_std: ${oc.select:data.density_noise_std,0.0}")
    assert "oc.select" in text
    run_dir = saved_run(tmp_path, text, **({} if data_noise is None else {"data__density_noise_std": data_noise}))
    assert run_config(run_dir).model.renderer.field.density_noise_std == expected


@pytest.mark.parametrize(("sweeper", "expected"), [
    ("_target_: hydra._internal.core_plugins.basic_sweeper.BasicSweeper\n    params:\n"
     "      seed: ${oc.env:NERFEXP_TEST_SECRET}\n      hierarchical: true,false", 2),
    ("_target_: hydra_plugins.hydra_optuna_sweeper.optuna_sweeper.OptunaSweeper\n"
     "    n_trials: ${oc.decode:'7'}", None),
    ("_target_: ${oc.env:NERFEXP_TEST_SECRET}\n    n_trials: 5", 5),
])
def test_a_sweeps_multirun_yaml_is_read_as_data(tmp_path, monkeypatch, sweeper, expected):
    monkeypatch.setenv("NERFEXP_TEST_SECRET", "0,1,2")  # three seeds, were it read: 6 jobs
    (tmp_path / "multirun.yaml").write_text(f"hydra:\n  sweeper:\n    {sweeper}\n  overrides:\n    task: []\n")
    assert planned_jobs(tmp_path) == expected


def snapshot(folder: Path) -> dict:
    """Every file under ``folder``: its size and modification time, to show nothing was written or replaced."""
    return {p.relative_to(folder): (p.stat().st_size, p.stat().st_mtime_ns) for p in folder.rglob("*")}


# where a crafted run puts the payload: (the dotted key it is written at, how the refusal names it)
PAYLOAD_FORMS = {
    "a value": ("view_dependence.direction_encoding", "{key}={value!r} uses the resolver oc.create"),
    "an escaped value": ("encoding.direction", "{key}={value!r} holds an escaped interpolation"),
    "an escaped list item": ("scale.skips", "{key}.0={value!r} holds an escaped interpolation"),
    "an escaped key": ("model.renderer", "the key {item!r} holds '${{'"),
}


@pytest.fixture(params=PAYLOAD_FORMS)
def created(request, tiny_run, tmp_path) -> tuple[Path, Path, str]:
    """A copy of a finished run whose saved config makes, with the resolver ``oc.create``, a node that builds
    ``torch.load`` of a crafted pickle (``weights_only: false``), written as one of ``PAYLOAD_FORMS`` (as
    the call, or escaped, which one resolution turns into the call); the payload's marker file; the start of
    the line refusing it."""
    run_dir, marker = tmp_path / "shared_run", tmp_path / "payload_ran"
    shutil.copytree(tiny_run, run_dir)
    torch.save({"weights": Payload(marker)}, tmp_path / "crafted.pt")
    value = f"${{oc.create:{{_target_: torch.load, f: '{tmp_path / 'crafted.pt'}', weights_only: false}}}}"
    key, refusal = PAYLOAD_FORMS[request.param]
    value = value if request.param == "a value" else "\\" + value
    config_path = run_dir / ".hydra" / "config.yaml"
    config = yaml.safe_load(config_path.read_text())
    *parents, leaf = key.split(".")
    section = config
    for name in parents:
        section = section[name]
    if request.param == "an escaped key":
        section[leaf][value] = 1
    else:
        section[leaf] = [value] if request.param == "an escaped list item" else value
    config_path.write_text(yaml.safe_dump(config))
    return run_dir, marker, f"{config_path}: {refusal.format(key=key, value=value, item=f'{key}.{value}')}"


def refused(script: str, line: str, start: str) -> bool:
    return line.startswith(f"{script}: error: {start}") and "a run directory from elsewhere is read as data" in line


@pytest.mark.slow
@pytest.mark.parametrize("created", ["a value", "an escaped value"], indirect=True)  # every form: in-process below
def test_a_node_a_resolver_creates_is_refused_before_anything_is_built(created, tmp_path):
    run_dir, marker, start = created
    before = snapshot(run_dir)
    result = run_nerfexp(str(run_dir), cwd=tmp_path, script="nerfexp-eval")
    assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr[-3000:]
    (line,) = [line for line in result.stderr.splitlines() if "error" in line]
    assert refused("nerfexp-eval", line, start), line
    assert not marker.exists() and snapshot(run_dir) == before


@pytest.mark.slow
@pytest.mark.parametrize("script", ["nerfexp-eval", "nerfexp-render", "nerfexp-export", "nerfexp-view"])
def test_so_it_is_by_every_command_that_reads_a_run_back(created, script):
    # in the process (the same one line as above, as eval's subprocess shows): the view never starts serving
    run_dir, marker, start = created
    main = {"nerfexp-eval": evaluate.main, "nerfexp-render": render.main, "nerfexp-export": export.main,
            "nerfexp-view": view.main}[script]
    before = snapshot(run_dir)
    with pytest.raises(SystemExit) as ended:
        main([str(run_dir)])
    assert refused(script, str(ended.value), start), str(ended.value)
    assert not marker.exists() and snapshot(run_dir) == before


@pytest.mark.slow
@pytest.mark.parametrize("created", ["an escaped list item"], indirect=True)
def test_so_it_is_when_a_checkpoint_of_an_earlier_nerfexp_is_resumed(created, tmp_path, tiny):
    # a checkpoint recording no settings is compared with its run directory's saved config, read as data
    run_dir, marker, start = created
    checkpoint = run_dir / "checkpoints" / "last.ckpt"
    state = torch.load(checkpoint, weights_only=True)
    del state["nerfexp_settings"]
    torch.save(state, checkpoint)
    result = run_nerfexp(*tiny, "scale.steps=90", f"resume={checkpoint}", f"hydra.run.dir={tmp_path / 'resumed'}",
                         cwd=tmp_path)
    assert refused("nerfexp", one_error_line(result), start), result.stderr[-2000:]
    assert not marker.exists() and not (tmp_path / "resumed").exists()


@pytest.mark.slow
def test_the_readers_environment_never_reaches_what_is_built_or_written(tiny_run, tmp_path, monkeypatch, capsys):
    from nerfexp.commands.evaluate import main  # in the process: the environment is the test's

    secret = "the-readers-secret"
    monkeypatch.setenv("NERFEXP_TEST_SECRET", secret)
    run_dir = tmp_path / "shared_run"
    shutil.copytree(tiny_run, run_dir)
    config_path = run_dir / ".hydra" / "config.yaml"
    config = yaml.safe_load(config_path.read_text())
    config["data"]["n_test"] = "${oc.env:NERFEXP_TEST_SECRET}"  # built: refused
    config_path.write_text(yaml.safe_dump(config))
    before = snapshot(run_dir)
    with pytest.raises(SystemExit) as ended:
        main([str(run_dir)])
    assert str(ended.value).startswith(f"nerfexp-eval: error: {config_path}: data.n_test=")
    assert secret not in str(ended.value)
    assert snapshot(run_dir) == before
    config["data"]["n_test"] = 2  # now only where training alone reads it: never read
    config["logger"]["save_dir"] = config["trainer"]["default_root_dir"] = "${oc.env:NERFEXP_TEST_SECRET}"
    config_path.write_text(yaml.safe_dump(config))
    before = snapshot(run_dir)
    main([str(run_dir)])
    written = [run_dir / path for path, stat in snapshot(run_dir).items() if before.get(path) != stat]
    assert run_dir / "eval.json" in written and secret not in capsys.readouterr().out
    assert not [path for path in written if path.is_file() and secret.encode() in path.read_bytes()]
    assert not [path for path in tmp_path.rglob("*") if secret in str(path)]


def test_a_saved_config_never_chooses_the_lpips_weights_its_reader_scores_with(tmp_path, saved_text):
    # the author's run names its own weights file, says it is the published one (lpips_custom false) or its own:
    # either way the reader's evaluation reads nerfexp's defaults, and what the reader sets on the command line
    for custom in (False, True):
        (tmp_path / str(custom)).mkdir()
        run_dir = saved_run(tmp_path / str(custom), saved_text, model__lpips=True, model__lpips_custom=custom,
                            model__lpips_weights=str(tmp_path / "author.pth"))
        cfg = run_config(run_dir)
        assert (cfg.model.lpips, cfg.model.lpips_weights, cfg.model.lpips_custom) == ("auto", None, False)
        mine = run_config(run_dir, ["model.lpips_weights=/mine.pth", "model.lpips_custom=true"])
        assert (mine.model.lpips, mine.model.lpips_weights, mine.model.lpips_custom) == ("auto", "/mine.pth", True)


def test_a_run_saved_before_lpips_custom_reads_back_with_it(tmp_path, saved_text):
    config = yaml.safe_load(saved_text)
    del config["model"]["lpips_custom"]  # an earlier nerfexp's run
    run_dir = saved_run(tmp_path, yaml.safe_dump(config))
    assert run_config(run_dir).model.lpips_custom is False
    assert run_config(run_dir, ["model.lpips_custom=true"]).model.lpips_custom is True


# Only the classes a key's owner allows are built at that key: those nerfexp's own config files name there
# (nerfexp.rundir.saved_configs.named_targets), so that a logger planted under the renderer builds nothing.

LOGGERS = {"lightning.pytorch.loggers.CSVLogger", "lightning.pytorch.loggers.MLFlowLogger",
           "lightning.pytorch.loggers.TensorBoardLogger", "lightning.pytorch.loggers.WandbLogger"}
ENCODINGS = {"nerfexp.nerf.encodings.IdentityEncoding", "nerfexp.nerf.encodings.PositionalEncoding"}


def test_the_classes_a_key_allows_are_those_nerfexps_own_files_name_there_or_reference_there():
    named = named_targets()
    assert named["logger"] == LOGGERS  # conf/logger/*.yaml
    assert named["model.renderer.grid"] == {"nerfexp.nerf.occupancy.OccupancyGrid"}  # ${acceleration.grid}
    assert named["model.appearance_fit"] == {"nerfexp.nerf.appearance.CodeFit"}  # ${appearance.fit}
    assert named["model.renderer.field"] == {"nerfexp.nerf.fields.NeRFField"}  # conf/field/, @package
    # ${view_dependence} in conf/field/, whose head holds ${encoding.direction}: carried through both
    assert named["model.renderer.field.view_head.direction_encoding"] == ENCODINGS
    assert named["model.renderer.field.position_encoding"] == {*ENCODINGS, "nerfexp.nerf.hashgrid.HashGridEncoding"}
    assert named["model.optimizer"] == {"torch.optim.Adam", "nerfexp.training.optimizers.LazyAdam"}  # the sweeps'
    assert named["trainer.plugins.0"] == {"nerfexp.training.checkpoints.AtomicCheckpointIO"}
    assert not any(key.startswith("model.renderer.") and LOGGERS & classes for key, classes in named.items())


@pytest.mark.parametrize("overrides", [[], ["logger=csv", "acceleration=occupancy", "trainer=ddp"],
                                       ["logger=mlflow", "view_dependence=sh", "encoding=none"],
                                       ["encoding=hashgrid", "hierarchical=proposal", "appearance=embedding",
                                        "test_cameras=refined", "camera_opt=so3xr3", "contraction=mipnerf360"],
                                       ["view_dependence=ref", "model.optimizer._target_=torch.optim.SGD"],
                                       ["+sweeps=sparse_tables"]])
def test_every_target_of_nerfexps_own_configs_is_allowed_at_its_key_as_written_and_resolved(tmp_path, overrides):
    with initialize_config_module("nerfexp.conf", version_base=None):
        cfg = compose("config", overrides=[*TINY, *overrides])
    check_targets(OmegaConf.to_container(cfg, resolve=False), tmp_path)
    run_dir = saved_run(tmp_path, OmegaConf.to_yaml(cfg))  # as the commands read it: resolved, training's keys out
    assert run_config(run_dir).model.renderer.field._target_ == "nerfexp.nerf.fields.NeRFField"


PLANTED = {"_target_": "lightning.pytorch.loggers.MLFlowLogger", "experiment_name": "planted"}


@pytest.mark.parametrize("key", ["model.renderer.grid", "model.renderer.field.view_head", "trainer.plugins.1",
                                 "model.appearance_fit", "data.planted", "planted"])
def test_a_logger_planted_at_another_key_is_refused_naming_the_file_the_key_and_the_class(tmp_path, saved_text, key):
    config = yaml.safe_load(saved_text)
    if key == "trainer.plugins.1":
        config["trainer"]["plugins"].append(PLANTED)
    else:
        put(config, key, PLANTED) if key.count(".") else config.update({key: PLANTED})
    run_dir = saved_run(tmp_path, yaml.safe_dump(config))
    with pytest.raises(ConfigError) as raised:
        run_config(run_dir)
    named = sorted(named_targets().get(key, ()))
    expected = f"its configs name {', '.join(named)} there" if named else "its configs build nothing there"
    assert str(raised.value) == (
        f"{run_dir / '.hydra' / 'config.yaml'}: {key}._target_='lightning.pytorch.loggers.MLFlowLogger' is not a "
        f"class nerfexp builds at {key} ({expected}): a run directory from elsewhere is read as data, never run")


def test_a_reference_that_lands_a_section_where_another_belongs_is_refused_once_resolved(tmp_path, saved_text):
    run_dir = saved_run(tmp_path, saved_text, model__appearance_fit="${model.renderer.field}")
    with pytest.raises(ConfigError) as raised:
        run_config(run_dir)
    assert str(raised.value).startswith(
        f"{run_dir / '.hydra' / 'config.yaml'}: model.appearance_fit._target_='nerfexp.nerf.fields.NeRFField' is "
        "not a class nerfexp builds at model.appearance_fit (its configs name nerfexp.nerf.appearance.CodeFit there)")


def test_another_torch_optimizer_is_allowed_where_nerfexp_names_one_and_nowhere_else(tmp_path, saved_text):
    assert run_config(saved_run(tmp_path, saved_text, model__optimizer___target_="torch.optim.SGD"))
    run_dir = saved_run(tmp_path, saved_text, model__optimizer___target_="torch.optim.Adam",
                        model__renderer__grid={"_target_": "torch.optim.SGD"})
    with pytest.raises(ConfigError, match="model.renderer.grid._target_='torch.optim.SGD' is not a class nerfexp "
                                          "builds at model.renderer.grid"):
        run_config(run_dir)


@settings(deadline=None)  # a class's first check imports its module (a scene's imports its format's packages)
@given(st.lists(st.from_regex(r"[a-z][a-z_]{0,8}", fullmatch=True), min_size=1, max_size=4).map(".".join),
       st.sampled_from(sorted(set().union(*named_targets().values()))))
def test_at_a_key_nerfexps_files_build_nothing_at_no_class_is_built(key, target):
    if key in named_targets():  # one of nerfexp's own sections: its classes (and their families') only
        return
    config: dict = {}
    put_new(config, key, {"_target_": target})
    with pytest.raises(ConfigError, match=f"{key}._target_='{target}' is not a class nerfexp builds at {key} "
                                          r"\(its configs build nothing there\)"):
        check_targets(config, Path("planted.yaml"))


def put_new(config: dict, dotted: str, value) -> None:
    """Set ``value`` at ``dotted`` in the plain dict ``config``, making the sections on the way."""
    *parents, leaf = dotted.split(".")
    for key in parents:
        config = config.setdefault(key, {})
    config[leaf] = value


def test_nerfexp_eval_refuses_a_planted_logger_before_it_creates_anything(tmp_path, saved_text, monkeypatch):
    monkeypatch.setenv("MLFLOW_ALLOW_FILE_STORE", "true")  # MLflow would make its plain-file store
    store = tmp_path / "planted_store"
    (tmp_path / "run").mkdir()
    run_dir = saved_run(tmp_path / "run", saved_text,
                        model__renderer__grid={**PLANTED, "tracking_uri": f"file://{store}"})
    (run_dir / "checkpoints").mkdir()
    (run_dir / "checkpoints" / "last.ckpt").write_bytes(b"never read")
    before = snapshot(run_dir)
    result = run_nerfexp(str(run_dir), cwd=tmp_path, script="nerfexp-eval")
    assert one_error_line(result, "nerfexp-eval").startswith(
        f"nerfexp-eval: error: {run_dir / '.hydra' / 'config.yaml'}: model.renderer.grid._target_="
        "'lightning.pytorch.loggers.MLFlowLogger' is not a class nerfexp builds at model.renderer.grid")
    assert not store.exists() and snapshot(run_dir) == before
    assert sorted(path.name for path in tmp_path.iterdir()) == ["run"]
