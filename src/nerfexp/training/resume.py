"""Resuming a run (``resume=CHECKPOINT``): a checkpoint records the settings it was trained with, and a
run continues it only with the same ones, so that a resumed run is the run its record says it is.

Settings are a config's leaves as plain data, ``{dotted key: value}`` (``flat_settings``). Those under
``MAY_DIFFER`` change how a run is carried out, not what it trains, and may differ on resuming;
``results.json`` records each that did (``resumes``). Every other setting must equal the checkpoint's:
the model, the data (where the scene lies, ``data.root``, aside), the data module, the seed, the
precision, the learning rates and their schedule. A checkpoint of an earlier nerfexp, which records no
settings, is compared with the config saved in its run directory (``.hydra/config.yaml``, before Hydra
writes this run's there); one that lies in no run directory, with the network's shapes alone
(``nerfexp.products.trained.check_weights``, called by the command).

A job reads the checkpoint once (``read_resumed``), keeping of it only what resuming needs (``Resumed``):
Lightning reads it again, whole, to continue training from it.
"""

import copy
import functools
import json
from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple

import torch
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from nerfexp.config_keys import leaves, source_key
from nerfexp.errors import NerfexpError, callback_refusals
from nerfexp.rundir.labels import LABELS
from nerfexp.rundir.layout import RUN_CONFIG
from nerfexp.rundir.trained import current_settings, read_checkpoint, run_config
from nerfexp.training.precision import fill_precision

SETTINGS = "nerfexp_settings"  # a checkpoint's key: {"settings": flat_settings, "choices": config group -> option}
RESUMES = "nerfexp_resumes"  # a checkpoint's key: the record of each resume that led to it (``resume_record``)

# Keys (with what lies under them) whose values may differ from the checkpoint's, and why
MAY_DIFFER = (
    "resume",
    "scale.steps", "trainer.max_steps",  # to train further; the learning-rate decay then spans the new total
    "scale.chunk", "model.chunk",  # rays rendered at once: memory, not results
    "scale.val_every", "trainer.val_check_interval",  # when validations and checkpoints happen
    "trainer.enable_progress_bar", "trainer.enable_model_summary", "trainer.log_every_n_steps",  # what is shown
    "logger",  # where metrics are logged
    "callbacks",  # checkpoints (where, how often) and the guards, which act only on a failing step
    "trainer.default_root_dir",  # the run's directory
    "data.root",  # where the scene lies, not what it is
    "data.catalog", "data.mirror",  # where a scene by name is looked up and downloaded from (its digest is checked)
    # where it runs: the processes share each global batch, the same objective (nerfexp.data.rays.RandomRays)
    "trainer.accelerator", "trainer.devices", "trainer.num_nodes", "trainer.strategy",
    "threads",  # torch's threads: how fast, not what is trained
    "test_budgets",  # when the test views are scored during training, not what is trained (nerfexp.training.budgets)
    "model.compile",  # the same networks, compiled
    "model.optimizer.fused",  # the same update, by one kernel or a loop
    "trainer.plugins",  # how checkpoints are written (nerfexp.training.checkpoints), not what is trained
    "model.lpips", "model.lpips_weights", "model.lpips_custom",  # what the evaluations score, not what is trained
    *LABELS,  # tags and notes: what the run is for, not what it trains (nerfexp.rundir.labels)
)
DERIVED = ("data.near", "data.far")  # null in a config: set from the scene (fill_ray_bounds), which is compared


def may_differ(key: str) -> bool:
    """Whether ``key`` (dotted) is, or lies under, one of ``MAY_DIFFER``."""
    return any(key == prefix or key.startswith(f"{prefix}.") for prefix in MAY_DIFFER)


def flat_settings(cfg: DictConfig, skip=lambda key: False) -> dict[str, object]:
    """``cfg``'s leaves as ``{dotted key: value}`` (``nerfexp.config_keys.leaves``: resolved, a list is one
    leaf, as a list; a value made from Hydra's runtime kept as its text; a mandatory value not set as
    ``"???"``), apart from ``hydra`` and the keys ``skip`` names."""
    return dict(leaves(cfg, skip=lambda key, node: skip(key)))


def group_choices(choices: Mapping) -> dict[str, str]:
    """The option chosen in each of nerfexp's config groups, from Hydra's ``hydra.runtime.choices`` (Hydra's
    own groups, and groups left empty, aside)."""
    return {group: str(option) for group, option in choices.items()
            if not group.startswith("hydra") and option is not None}


def checkpoint_settings(cfg: DictConfig, choices: dict[str, str]) -> dict:
    """What a checkpoint records of the run that trained it (``SETTINGS``): every setting of ``cfg`` (a run's
    resolved config, ``flat_settings``) and the config groups' ``choices``, as plain data."""
    return {"settings": flat_settings(cfg), "choices": dict(choices)}


class Resumed(NamedTuple):
    """What resuming needs of a checkpoint (``read_resumed``): its record and the shapes of its weights."""

    step: int  # the optimizer steps it had taken (its global_step)
    settings: dict | None  # what it records of the run that trained it (SETTINGS); None: an earlier nerfexp's
    resumes: list[dict]  # the resumes that led to it (RESUMES)
    weights: dict[str, torch.Tensor]  # its state_dict on the meta device: names and shapes, no values


def read_resumed(checkpoint: Path) -> Resumed:
    """Checkpoint ``checkpoint``'s ``Resumed``, read as data (``read_checkpoint``; its errors name the file).
    A process reads a file once (while it is unchanged): Hydra checks a single run (``ResumeCheck``) and
    then runs its job in one process, and nothing passes from the callback to the job but this."""
    path = Path(checkpoint)
    version = None  # no file: read_checkpoint says so
    if path.is_file():
        found = path.stat()
        version = (found.st_ino, found.st_size, found.st_mtime_ns)
    return _read_resumed(path, path.resolve(), version)


@functools.lru_cache(maxsize=1)
def _read_resumed(path: Path, resolved: Path, version: tuple | None) -> Resumed:
    """``read_resumed`` of ``path`` (the file ``resolved`` as ``version``: inode, size, modification time)."""
    state = read_checkpoint(path)
    settings, resumes = state.get(SETTINGS), state.get(RESUMES)
    weights = {name: value.to("meta") if isinstance(value, torch.Tensor) else value
               for name, value in state["state_dict"].items()}
    return Resumed(state["global_step"], settings if isinstance(settings, dict) else None,
                   resumes if isinstance(resumes, list) else [], weights)


def recorded_settings(resumed: Resumed, checkpoint: Path) -> dict | None:
    """The settings (``checkpoint_settings``) that trained checkpoint ``checkpoint`` (``resumed``): as it
    records them, else (an earlier nerfexp's) those of its run directory's saved config while that is still
    the run's (``checkpoint`` is ``RUN/checkpoints/NAME.ckpt``), with no choices; None where neither exists."""
    if resumed.settings is not None:  # named as this version names them (a record of an earlier layout)
        return {**resumed.settings, "settings": current_settings(resumed.settings.get("settings", {}))}
    run_dir = Path(checkpoint).resolve().parent.parent
    if not (run_dir / RUN_CONFIG).is_file():
        return None
    return {"settings": flat_settings(run_config(run_dir), skip=may_differ), "choices": {}}


ABSENT = object()  # a setting one side does not have


def shown(value) -> str:
    """A setting's value as it is written on the command line: ``null``, ``true``, ``[1, 2]``, ``0.005``."""
    if value is ABSENT:
        return "(not set)"
    if value is None or isinstance(value, bool | list | dict):
        return json.dumps(value)
    return str(value)


def differing(recorded: dict, cfg: DictConfig, current: dict[str, object], choices: dict[str, str]) -> list[tuple]:
    """The settings of ``recorded`` (``checkpoint_settings``) that ``current`` (``flat_settings`` of this run's
    ``cfg``, with its ``choices``) sets otherwise, outside ``MAY_DIFFER``, as ``(name, checkpoint's value,
    this run's value)`` in the order of the checkpoint's keys, each named as the user sets it
    (``nerfexp.config_keys.source_key``): a config group whose option differs (``encoding``) stands for the
    keys under it. A ``DERIVED`` value this run leaves null, and a setting the checkpoint does not record
    (one added by a later nerfexp), are not compared."""
    changed_groups = {group.replace("/", "."): (option, choices.get(group, ABSENT))
                      for group, option in recorded.get("choices", {}).items()
                      if choices.get(group, ABSENT) != option and not may_differ(group.replace("/", "."))}
    found: dict[str, tuple] = {}
    for key, was in recorded["settings"].items():
        now = current.get(key, ABSENT)
        if may_differ(key) or now == was or (key in DERIVED and now is None):
            continue
        name = source_key(cfg, key)
        group = next((g for g in changed_groups if name == g or name.startswith(f"{g}.")), None)
        if group is not None:
            found.setdefault(group, (group, *changed_groups[group]))
        else:
            found.setdefault(name, (name, recorded["settings"].get(name, was), current.get(name, now)))
    return list(found.values())


def check_resume(cfg: DictConfig, choices: dict[str, str], checkpoint: Path) -> Resumed:
    """Checkpoint ``checkpoint``'s ``Resumed`` (``read_resumed``) where the run of ``cfg`` (its config group
    ``choices``) may continue it; else a NerfexpError in one line: settings that differ from those it was
    trained with (``differing``, each named with both values), or a checkpoint that has taken all of the
    run's steps (train further by raising ``scale.steps``, or score it with ``nerfexp-eval``)."""
    resumed = read_resumed(checkpoint)
    recorded = recorded_settings(resumed, checkpoint)
    if recorded is not None:
        current = flat_settings(cfg, skip=may_differ)
        if found := differing(recorded, cfg, current, choices):
            was = ", ".join(f"{name}={shown(value)}" for name, value, _ in found)
            now = ", ".join(f"{name}={shown(value)}" for name, _, value in found)
            raise NerfexpError(f"resume={checkpoint}: the checkpoint was trained with {was}; this run sets {now}: "
                               "resume with the checkpoint's settings or start a new run")
    step, max_steps = resumed.step, OmegaConf.select(cfg, "trainer.max_steps")
    if isinstance(max_steps, int) and step >= max_steps:
        steps = f"{source_key(cfg, 'trainer.max_steps')}={max_steps}"
        raise NerfexpError(f"resume={checkpoint}: the checkpoint has taken {step} steps, all of this run's ({steps}): "
                           f"raise {steps.split('=')[0]} to train further, or score it with nerfexp-eval "
                           f"{checkpoint}")
    return resumed


def resume_record(resumed: Resumed, checkpoint: Path, current: dict[str, object]) -> list[dict]:
    """The resumes that led to a run continued from checkpoint ``checkpoint`` (``resumed``) with the
    settings ``current`` (``flat_settings`` of its whole config): the checkpoint's own (``RESUMES``), then
    this one, ``{"step", "checkpoint", "changed": {key: [checkpoint's value, this run's]}}`` with the
    ``MAY_DIFFER`` settings it changed (none known for an earlier nerfexp's checkpoint)."""
    recorded = (resumed.settings or {}).get("settings", {})
    changed = {key: [was, current.get(key)] for key, was in recorded.items()
               if may_differ(key) and key != "resume" and current.get(key, ABSENT) != was}
    return [*resumed.resumes, {"step": resumed.step, "checkpoint": str(Path(checkpoint).resolve()),
                               "changed": changed}]


class ResumeCheck(Callback):
    """Hydra callback (``hydra.callbacks.resume``): a single run with ``resume=`` is checked
    (``check_resume``) before Hydra claims or writes its directory, so that a refused resume leaves the
    run it names as it was; its job then uses what this read (``read_resumed``). Each job of a sweep is
    checked by ``nerfexp.commands.train``. It stops with ``SystemExit``, whatever the check raised
    (``nerfexp.errors.callback_refusals``): Hydra turns a callback's exceptions into warnings and goes on."""

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        if config.get("resume") is None:
            return
        config = copy.deepcopy(config)
        with callback_refusals("the resume check"):
            fill_precision(config)  # as the job will: a checkpoint records the precision auto chose
            check_resume(config, group_choices(config.hydra.runtime.choices), Path(config.resume))
