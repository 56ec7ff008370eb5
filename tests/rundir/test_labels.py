"""A run's labels (``tags``, ``notes``; nerfexp.rundir.labels): set like any setting, refused in one line where
they are not short texts or hold an interpolation (never resolved: what a run records is what its saved config
says), recorded by the run and given to its loggers, free to change on resuming. That they are never part of a
variant: tests/report/test_report.py."""

import contextlib
import json
import shutil
from types import SimpleNamespace

import pytest
import yaml
from hydra import compose, initialize_config_module
from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger
from omegaconf import OmegaConf
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.plugins.hparams.plugin_data_pb2 import HParamsPluginData

from nerfexp.commands import evaluate
from nerfexp.errors import ConfigError
from nerfexp.rundir.labels import NO_LABELS, run_labels
from nerfexp.rundir.layout import RUN_CONFIG
from nerfexp.settings.checks import check_composition, check_settings
from nerfexp.settings.unused import unused_settings
from nerfexp.training.precision import fill_precision
from nerfexp.training.recorders import RunRecorder
from nerfexp.training.resume import check_resume, checkpoint_settings, flat_settings, group_choices, resume_record
from tests.helpers import TINY, one_error_line, read_json, run_nerfexp, without_overrides

LABELLED = ["tags=[baseline,lego]", "notes=first try"]


@pytest.fixture(scope="module")
def hydra_configs():
    with initialize_config_module("nerfexp.conf", version_base=None):
        yield


def composed(*overrides, hydra: bool = False):
    """The TINY config with ``overrides`` (with Hydra's own section where ``hydra``: its choices)."""
    return compose("config", overrides=[*TINY, *overrides, "trainer.default_root_dir=."], return_hydra_config=hydra)


def test_tags_and_notes_are_settings_that_a_run_records_and_none_is_unused(hydra_configs):
    assert run_labels(composed()) == {"tags": [], "notes": None}  # none by default
    cfg = composed(*LABELLED)
    check_settings(cfg)
    assert run_labels(cfg) == {"tags": ["baseline", "lego"], "notes": "first try"}
    assert unused_settings(cfg, [*TINY, *LABELLED]) == []
    assert unused_settings(composed("hierarchical=false", *LABELLED), LABELLED) == []
    recorded = checkpoint_settings(cfg, {})["settings"]  # what a checkpoint records of the run
    assert (recorded["tags"], recorded["notes"]) == (["baseline", "lego"], "first try")


LIST = ("tags={}: expected a list of at most 32 tags, each a text of 1 to 64 characters without control characters "
        "(tags=[baseline,lego]; a number quoted: tags=['2024'])")
NOTE = "notes={}: expected a text of 1 to 1000 characters without control characters, or null (none)"


@pytest.mark.parametrize(("override", "message"), [
    ("tags=baseline", LIST.format("baseline")),  # one text, not a list
    ("tags=[baseline,2024]", LIST.format("['baseline', 2024]")),  # a number: quoted it is a tag
    ("tags=[true]", LIST.format("[True]")),
    ("tags=['']", LIST.format("['']")),
    ("tags=['  ']", LIST.format("['  ']")),
    ("tags=[" + "x" * 65 + "]", LIST.format(f"['{'x' * 65}']")),
    ("tags=[" + ",".join(f"t{i}" for i in range(33)) + "]", LIST.format(str([f"t{i}" for i in range(33)]))),
    ("tags=['red\x1b[31m']", LIST.format("['red\\x1b[31m']")),  # a terminal's escape sequence
    ("notes='line one\nline two'", NOTE.format("'line one\\nline two'")),  # shown escaped: still one line
    ("notes=''", NOTE.format("")),
    ("notes=" + "x" * 1001, NOTE.format("x" * 1001)),
    ("notes=[a]", NOTE.format("['a']")),
])
def test_labels_that_are_not_short_texts_are_refused_in_one_line(hydra_configs, override, message):
    with pytest.raises(ConfigError) as error:
        check_settings(composed(override))
    assert str(error.value) == message
    assert len(str(error.value).splitlines()) == 1


def test_a_bad_label_on_the_command_line_is_one_line_before_any_work(tmp_path):
    run_dir = tmp_path / "run"
    result = run_nerfexp(*TINY, "notes='first\nsecond'", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert one_error_line(result) == f"nerfexp: error: {NOTE.format(repr('first' + chr(10) + 'second'))}"
    assert "second" not in result.stderr.replace(one_error_line(result), "")  # the newline printed as \n
    assert not run_dir.exists()


def test_the_loggers_hyperparameters_hold_the_labels(tmp_path):
    # labels that no override sets (a sweep file's): they reach the loggers all the same
    recorder = RunRecorder(str(tmp_path), {"encoding": "posenc", "seed": 0}, overrides=["seed=0"],
                           labels={"tags": ["baseline", "x|y"], "notes": "first try"})
    tensorboard = TensorBoardLogger(tmp_path, name="tensorboard", version="")
    table = CSVLogger(tmp_path, name="csv", version="")
    recorder.on_fit_start(SimpleNamespace(is_global_zero=True, loggers=[tensorboard, table]), None)
    tensorboard.experiment.flush()
    table.save()
    hparams = yaml.safe_load((tmp_path / "csv" / "hparams.yaml").read_text())
    assert json.loads(hparams["tags"]) == ["baseline", "x|y"] and hparams["notes"] == "first try"
    assert hparams["encoding"] == "posenc"
    events = EventAccumulator(str(tmp_path / "tensorboard"))
    events.Reload()
    content = events.PluginTagToContent("hparams")["_hparams_/session_start_info"]
    hparams = HParamsPluginData.FromString(content).session_start_info.hparams  # TensorBoard's HPARAMS view
    assert json.loads(hparams["tags"].string_value) == ["baseline", "x|y"]
    assert hparams["notes"].string_value == "first try"


def test_a_resume_may_change_the_labels_and_records_that_it_did(hydra_configs, tiny_run):
    checkpoint = tiny_run / "checkpoints" / "last.ckpt"
    cfg = composed(*LABELLED, "scale.steps=90", f"resume={checkpoint}", hydra=True)
    fill_precision(cfg)  # as a resume's check does
    resumed = check_resume(cfg, group_choices(cfg.hydra.runtime.choices), checkpoint)
    (record,) = resume_record(resumed, checkpoint, flat_settings(cfg))
    assert record["changed"]["tags"] == [[], ["baseline", "lego"]]
    assert record["changed"]["notes"] == [None, "first try"]


@pytest.mark.slow
def test_a_run_records_its_labels_in_its_files_and_in_tensorboard(tiny_run, tmp_path, tiny):
    run_dir = tmp_path / "run"
    shutil.copytree(tiny_run, run_dir)
    checkpoint = run_dir / "checkpoints" / "last.ckpt"
    result = run_nerfexp(*tiny, "scale.steps=90", *LABELLED, f"resume={checkpoint}", f"hydra.run.dir={run_dir}",
                         cwd=tmp_path)  # resumed with labels the run did not have: 30 more steps
    assert result.returncode == 0, result.stderr[-3000:]
    results, status = read_json(run_dir / "results.json"), read_json(run_dir / "status.json")
    assert (results["tags"], results["notes"]) == (["baseline", "lego"], "first try")
    assert (status["state"], status["tags"], status["notes"]) == ("finished", ["baseline", "lego"], "first try")
    assert results["resumes"][-1]["changed"]["tags"] == [[], ["baseline", "lego"]]
    declared = []  # each process's hyper-parameters, in its own event files: the first run's, the resumed one's
    for path in sorted((run_dir / "tensorboard").glob("events.out.tfevents.*")):
        events = EventAccumulator(str(path))
        events.Reload()
        with contextlib.suppress(KeyError):  # a file of the test's scores: no hyper-parameters
            content = events.PluginTagToContent("hparams")["_hparams_/session_start_info"]
            declared.append(HParamsPluginData.FromString(content).session_start_info.hparams)
    assert len(declared) == 2 and "tags" not in declared[0]
    hparams = declared[-1]
    assert json.loads(hparams["tags"].string_value) == ["baseline", "lego"]
    assert hparams["notes"].string_value == "first try"


# Labels are text, recorded as written: any interpolation in one (a resolver, a reference, text around one, an
# escaped one, one that cannot resolve) is refused before anything resolves it, named as the override gives it,
# or by its key where a config file sets it
PLAIN = ("expected plain text: tags and notes are recorded as written, never resolved, so they cannot hold '${' "
         "(an interpolation); write the text itself")
INTERPOLATED = [  # (override, the label as the composed config writes it)
    ("notes=${oc.env:HOME}", "notes=${oc.env:HOME}"),  # the two
    ('tags=["${now:%Y}"]', "tags=['${now:%Y}']"),
    ("notes=${seed}", "notes=${seed}"),
    ("notes='seed ${seed} of 3'", "notes=seed ${seed} of 3"),
    ("notes='\\${x}'", "notes=\\${x}"),  # escaped: resolved to the text ${x}, live again once saved
    ("tags=[a,'x${seed}']", "tags=['a', 'x${seed}']"),
    ("tags=${oc.decode:'[a, b]'}", "tags=${oc.decode:'[a, b]'}"),  # the whole list
    ("notes=${oc.env:NERFEXP_NO_SUCH_VARIABLE}", "notes=${oc.env:NERFEXP_NO_SUCH_VARIABLE}"),  # cannot resolve
    ("notes='${seed}\nsecond line'", "notes='${seed}\\nsecond line'"),  # shown escaped: still one line
]


@pytest.mark.parametrize(("override", "written"), INTERPOLATED)
def test_a_label_holding_an_interpolation_is_refused_in_one_line_and_never_recorded(hydra_configs, override,
                                                                                   written):
    cfg = composed(override, hydra=True)
    with pytest.raises(ConfigError) as error:
        check_composition(cfg, cfg.hydra)  # a single run's first check, a sweep's and each job's
    assert str(error.value) == f"{override if override.isprintable() else repr(override)}: {PLAIN}"
    with pytest.raises(ConfigError) as error:
        bare = without_overrides(cfg)
        check_composition(bare, bare.hydra)
    assert str(error.value) == f"{written}: {PLAIN}"
    assert len(str(error.value).splitlines()) == 1
    key = written.partition("=")[0]
    assert run_labels(cfg)[key] == NO_LABELS[key]  # a job's status.json, written before the check stops it


@pytest.mark.parametrize("labels", [["notes=first try", "tags=[baseline,lego]"],
                                    ["notes='costs $5 {approx}, 100% of it'", "tags=['$HOME','{seed}','$', a$b]"]])
def test_plain_labels_pass_and_are_recorded_as_written(hydra_configs, labels):
    cfg = composed(*labels, hydra=True)
    check_composition(cfg, cfg.hydra)
    check_settings(cfg)
    recorded = run_labels(cfg)
    assert recorded == {key: OmegaConf.to_container(cfg, resolve=False)[key] for key in ("tags", "notes")}
    assert recorded == {"tags": OmegaConf.to_container(cfg.tags, resolve=True), "notes": cfg.notes}  # resolved


@pytest.mark.parametrize("arguments", [
    ["notes=${oc.env:HOME}"], ['tags=["${now:%Y}"]'],  # the issue's
    ["-m", "seed=0,1", "notes=${now:%Y}"], ["-m", "seed=0,1", "tags=[a],['${now:%Y}']"],  # a sweep, one of its jobs
])
def test_an_interpolated_label_on_the_command_line_is_one_line_before_anything_is_made(tmp_path, arguments):
    result = run_nerfexp(*arguments, *TINY, f"hydra.run.dir={tmp_path / 'run'}",
                         f"hydra.sweep.dir={tmp_path / 'sweep'}", cwd=tmp_path)
    assert one_error_line(result) == f"nerfexp: error: {arguments[-1]}: {PLAIN}"
    assert list(tmp_path.iterdir()) == []


def test_a_sweep_files_interpolated_label_is_one_line_before_the_sweep_directory_is_made(tmp_path):
    configs = tmp_path / "configs" / "sweeps"
    configs.mkdir(parents=True)
    (configs / "dated.yaml").write_text("# @package _global_\nnotes: ${now:%Y-%m-%d}\nhydra:\n  mode: MULTIRUN\n")
    sweep = tmp_path / "sweep"
    result = run_nerfexp(f"hydra.searchpath=[file://{configs.parent}]", "+sweeps=dated", *TINY,
                         f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert one_error_line(result) == f"nerfexp: error: notes=${{now:%Y-%m-%d}}: {PLAIN}"
    assert not sweep.exists()


@pytest.mark.slow
def test_a_run_with_labels_records_what_its_saved_config_says_and_is_read_back(tmp_path, tiny):
    run_dir = tmp_path / "run"
    labels = ["notes='costs $5 {approx}, 100% of it'", "tags=[baseline,'$HOME','{seed}']"]
    result = run_nerfexp(*tiny, *labels, f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    saved = OmegaConf.to_container(OmegaConf.load(run_dir / RUN_CONFIG), resolve=False)
    expected = {"tags": ["baseline", "$HOME", "{seed}"], "notes": "costs $5 {approx}, 100% of it"}
    assert {key: saved[key] for key in expected} == expected
    for record in ("results.json", "status.json"):
        assert {key: read_json(run_dir / record)[key] for key in expected} == expected
    evaluate.main([str(run_dir)])  # nerfexp-eval reads the run back
    assert read_json(run_dir / "eval.json")["test_psnr"] > 0
