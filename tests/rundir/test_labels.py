"""A run's labels (``tags``, ``notes``; nerfexp.rundir.labels): set like any setting, refused in one line where
they are not short texts, recorded by the run and given to its loggers, free to change on resuming. That they
are never part of a variant: tests/report/test_report.py."""

import contextlib
import json
import shutil
from types import SimpleNamespace

import pytest
import yaml
from hydra import compose, initialize_config_module
from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.plugins.hparams.plugin_data_pb2 import HParamsPluginData

from nerfexp.errors import ConfigError
from nerfexp.rundir.labels import run_labels
from nerfexp.settings.checks import check_settings
from nerfexp.settings.unused import unused_settings
from nerfexp.training.precision import fill_precision
from nerfexp.training.recorders import RunRecorder
from nerfexp.training.resume import check_resume, checkpoint_settings, flat_settings, group_choices, resume_record
from tests.helpers import TINY, one_error_line, read_json, run_nerfexp

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
