"""A check that fails is a refusal: a component of one's own (a config group option added through
``hydra.searchpath``, docs/developing.md) that names a class without an argument it needs is one line naming the key
before the run directory is made, and any exception a check raises (Hydra's callbacks, the settings check of a run
read back) stops the command in one line, never Hydra's warning followed by the run."""

import json

import pytest
import yaml
from omegaconf import OmegaConf

import nerfexp.rundir.claim
import nerfexp.rundir.trained
import nerfexp.settings.checks
import nerfexp.training.resume
from nerfexp.rundir.layout import LAST_CHECKPOINT, RUN_CONFIG
from tests.helpers import TINY, one_error_line, run_nerfexp, tiny_config

# Options of one's own, each naming one of nerfexp's classes (or the tests' toy sampler) without an argument it
# needs: (group, option file's content, the refusal). The field builds a colour head with its width (``in_features``,
# ``NeRFField``'s ``view_head: Callable[[int], ViewDependence]``), so that one is never asked of the option.
OPTIONS = {
    "the proposal sampler bare": (
        "sampler", {"_target_": "nerfexp.nerf.proposal.ProposalSampler", "_partial_": True},
        "sampler: ProposalSampler needs network, n_samples, n_final (not given)"),
    "a sampler of one's own without its size": (
        "sampler", {"_target_": "tests.components.toy.MidpointSampler", "_partial_": True},
        "sampler: MidpointSampler needs n_samples (not given)"),
    "a colour head without its encoding": (
        "view_dependence", {"_target_": "nerfexp.nerf.fields.MLPViewDependence", "_partial_": True, "hidden": 16},
        "view_dependence: MLPViewDependence needs direction_encoding (not given)"),
    "an encoding without its frequencies": (
        "encoding", {"position": {"_target_": "nerfexp.nerf.encodings.PositionalEncoding"},
                     "direction": {"_target_": "nerfexp.nerf.encodings.PositionalEncoding", "n_freqs": 4}},
        "encoding.position: PositionalEncoding needs n_freqs (not given)"),
}


@pytest.mark.parametrize("case", OPTIONS)
def test_an_option_of_ones_own_without_an_argument_its_class_needs_is_one_line_before_the_run(tmp_path, case):
    group, content, message = OPTIONS[case]
    (tmp_path / "conf" / group).mkdir(parents=True)
    (tmp_path / "conf" / group / "mine.yaml").write_text(yaml.safe_dump(content))
    result = run_nerfexp(*TINY, f"hydra.searchpath=[file://{tmp_path / 'conf'}]", f"{group}=mine",
                         f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert one_error_line(result) == f"nerfexp: error: {message}"
    assert "warn" not in result.stderr.lower()
    assert not (tmp_path / "run").exists()


class Broken(Exception):
    """An error no check means to raise."""


def broken(*args, **kwargs):
    raise Broken("'n_samples'")


# Each check that a single run's Hydra callbacks make before the run directory is made: (the module and the name of
# a function it calls, made to raise; the overrides that reach it; the check, as the refusal names it)
CALLBACK_CHECKS = {
    "the settings check": (nerfexp.settings.checks, "check_world_rays", [], "the settings check"),
    "the unused settings check": (nerfexp.settings.checks, "check_used", [], "the settings check"),
    "the resume check": (nerfexp.training.resume, "check_resume", ["resume={checkpoint}"], "the resume check"),
    "the run directory's check": (nerfexp.rundir.claim, "admit_run", [], "the run directory's check"),
}


@pytest.mark.parametrize("case", CALLBACK_CHECKS)
def test_a_check_that_fails_stops_a_run_in_one_line_before_its_directory_is_made(tmp_path, monkeypatch, case):
    module, name, overrides, check = CALLBACK_CHECKS[case]
    monkeypatch.setattr(module, name, broken)
    checkpoint = tmp_path / "elsewhere" / "last.ckpt"
    checkpoint.parent.mkdir()
    checkpoint.write_bytes(b"never read")
    result = run_nerfexp(*TINY, *(o.format(checkpoint=checkpoint) for o in overrides),
                         f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert one_error_line(result) == f"nerfexp: error: {check} failed on this config (Broken: 'n_samples')"
    assert "warn" not in result.stderr.lower()
    assert not (tmp_path / "run").exists()


# Each check of a run read back before its checkpoint is read: (the module and the name of a function it calls, made to
# raise; the check, as the refusal names it: RUN, the run's directory)
READ_BACK_CHECKS = {
    "the check of its saved config": (nerfexp.rundir.trained, "check_own_shapes",
                                      "the check of {run}/.hydra/config.yaml"),
    "the settings check": (nerfexp.settings.checks, "check_world_rays", "the settings check"),
}


@pytest.mark.parametrize("case", READ_BACK_CHECKS)
def test_a_check_that_fails_stops_a_command_reading_a_run_back_in_one_line(tmp_path, monkeypatch, case):
    module, name, check = READ_BACK_CHECKS[case]
    run_dir = tmp_path / "run"
    (run_dir / RUN_CONFIG).parent.mkdir(parents=True)
    OmegaConf.save(tiny_config(), run_dir / RUN_CONFIG)
    (run_dir / LAST_CHECKPOINT).parent.mkdir()
    (run_dir / LAST_CHECKPOINT).write_bytes(b"never read: the check comes first")
    monkeypatch.setattr(module, name, broken)
    result = run_nerfexp(str(run_dir), "data.n_test=1", cwd=tmp_path, script="nerfexp-eval")
    assert one_error_line(result, "nerfexp-eval") == (f"nerfexp-eval: error: {check.format(run=run_dir)} failed on "
                                                      "this config (Broken: 'n_samples')")


def test_a_sweeps_job_with_such_an_option_fails_in_that_line_before_any_work(tmp_path):
    group, content, message = OPTIONS["the proposal sampler bare"]
    (tmp_path / "conf" / group).mkdir(parents=True)
    (tmp_path / "conf" / group / "mine.yaml").write_text(yaml.safe_dump(content))
    result = run_nerfexp("-m", *TINY, f"hydra.searchpath=[file://{tmp_path / 'conf'}]", f"{group}=mine",
                         f"hydra.sweep.dir={tmp_path / 'sweep'}", cwd=tmp_path)
    assert one_error_line(result) == f"nerfexp: error: {message}"  # the job's directory is Hydra's, made first
    status = json.loads((tmp_path / "sweep" / "0" / "status.json").read_text())
    assert status["state"] == "failed" and status["error"] == f"ConfigError: {message}"
    assert not (tmp_path / "sweep" / "0" / "checkpoints").exists()
