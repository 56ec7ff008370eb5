"""A command line a page shows, checked as nerfexp checks its own before any work. ``nerfexp``'s: the run, or jobs
of its sweep that meet each of its values (the command line's sweeps and a sweep file's ``hydra.sweeper.params``
both), each composed by Hydra and put through the checks a run makes before its directory is made
(``nerfexp.settings.checks.SettingsCheck``: the groups' values, the settings' domains, a row's label, unused keys,
memory). Another console script's: its arguments, parsed by its own parser. Nothing is trained, downloaded or
read: what each command does is tested where that command is."""

import argparse
import contextlib
import importlib
import io

import tomllib
from hydra import compose, initialize_config_module
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.types import RunMode

from nerfexp.settings.checks import SettingsCheck
from tests.helpers import REPO

TRAIN = "nerfexp"
MULTIRUN = {"-m", "--multirun"}  # Hydra's flag for a sweep; every other word of a nerfexp line is an override
SCRIPTS = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]  # {program: module:function}


def parser(program: str) -> argparse.ArgumentParser:
    """The argument parser of the console script ``program`` (``nerfexp-report``): its command module's
    (``nerfexp.commands.start:report`` starts ``nerfexp.commands.report``)."""
    command = SCRIPTS[program].split(":")[1]
    return importlib.import_module(f"nerfexp.commands.{command}").build_parser()


def sweep_jobs(overrides: list[str]) -> list[list[str]]:
    """Jobs of the sweep ``overrides`` make in which each value of each of its axes is met at least once (the i-th
    job takes each axis's i-th value, or its last), not every combination: which values a component takes, and with
    which others, is its checks' to say (tests/test_settings.py); that a page's command line names only values the
    checks take is this one's. A later override of a key replaces an earlier one, as in Hydra's basic sweeper."""
    axes: dict[str, list[str]] = {}
    for override in OverridesParser.create().parse_overrides(overrides):
        key = override.get_key_element()
        axes.pop(key, None)
        axes[key] = ([f"{key}={value}" for value in override.sweep_string_iterator()] if override.is_sweep_override()
                     else [f"{key}={override.get_value_element_as_str()}"])
    return [[values[min(i, len(values) - 1)] for values in axes.values()]
            for i in range(max((len(values) for values in axes.values()), default=1))]


def jobs(overrides: list[str], multirun: bool) -> list[list[str]]:
    """The jobs of ``nerfexp OVERRIDES`` to check (``sweep_jobs``): the command line's sweeps, and those of the sweep
    file it adds (``+sweeps=NAME``'s ``hydra.sweeper.params``), the command line's value winning where both set a
    key. A ValueError where the command line sweeps but runs a single run (neither ``-m``, ``multirun``, nor a sweep
    file's ``hydra.mode: MULTIRUN``): Hydra refuses its sweep's value as ambiguous."""
    hydra = compose("config", overrides=sweep_jobs(overrides)[0], return_hydra_config=True).hydra
    sweeps = [override for override in OverridesParser.create().parse_overrides(overrides)
              if override.is_sweep_override()]
    if sweeps and not (multirun or hydra.mode == RunMode.MULTIRUN):
        raise ValueError(f"{sweeps[0].input_line}: a sweep's values in a single run (add -m)")
    basic = hydra.sweeper.get("_target_", "").endswith(".BasicSweeper")
    params = [f"{key}={value}" for key, value in (hydra.sweeper.get("params") or {}).items()] if basic else []
    return sweep_jobs([*params, *overrides])


def training_refusal(arguments: list[str]) -> str | None:
    """The line that stops ``nerfexp ARGUMENTS`` before any work (Hydra's, or nerfexp's checks'), for the first of
    the jobs checked that stops; None where every one would start."""
    with initialize_config_module("nerfexp.conf", version_base=None):
        try:
            overrides = [word for word in arguments if word not in MULTIRUN]
            for job in jobs(overrides, multirun=len(overrides) < len(arguments)):
                SettingsCheck().on_run_start(compose("config", overrides=job, return_hydra_config=True))
        except SystemExit as stopped:  # nerfexp's checks
            return str(stopped)
        except Exception as refused:  # Hydra's (no such option, no such key): the command stops there too
            return f"{type(refused).__name__}: {refused}"
    return None


def refusal(command: list[str]) -> str | None:
    """The line that stops ``command`` (a program of nerfexp's and its arguments) before any work; None where it
    would start."""
    program, *arguments = command
    if program == TRAIN:
        return training_refusal(arguments)
    stderr = io.StringIO()
    try:
        with contextlib.redirect_stderr(stderr):
            parser(program).parse_args(arguments)
    except SystemExit:
        return stderr.getvalue().strip()
    return None
