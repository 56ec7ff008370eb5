"""The settings' domains: every key of the composed config has a rule (``rule_of``), a rule being what is
expected, in words for the error, and the test (``nerfexp.domains``). A component's arguments have theirs beside
its class (``DOMAINS``: ``PositionalEncoding.DOMAINS``, ``BlenderScene.DOMAINS``, ...), read from the class the
config's ``_target_`` names (``component_rule``), so that a new component brings its own; the keys no component
owns (the model's, the trainer's, ...) have theirs in ``SCHEMA`` (fnmatch patterns, the first that matches rules).
A key that others read through a plain interpolation (the scale's sizes: ``model.optimizer.lr: ${scale.lr}``,
``sampler.n_coarse: ${scale.n_coarse}``) has the rules of the keys it lands in (``readers_rule``), so that a
component sized by a new ``scale.KEY`` brings that key's rule too, and none is listed here.

A key nothing covers is not a setting, so a new key in ``conf/`` cannot ship without a domain
(tests/test_settings.py composes every option of every group). Keys a user adds under a section that a
class takes as keyword arguments (``PASSED_ON``: ``+trainer.gradient_clip_val``, ``+callbacks.NAME.*``)
are that class's to check; its error is one line too (``nerfexp.commands.train.cli``). The domains are
read from the components' own constants (backgrounds, activations, the guards' actions, Lightning's
registries), so that a new choice there is a valid setting here.
"""

from collections.abc import Callable
from fnmatch import fnmatchcase
from typing import get_args, get_type_hints

from hydra.utils import get_class
from omegaconf import DictConfig, OmegaConf

from nerfexp.config_keys import readers
from nerfexp.data.pose_noise import POSE_NOISE_SETTING
from nerfexp.domains import (
    BOOLEAN,
    COUNT,
    FRACTION,
    INTEGER_LIMIT,
    LEARNING_RATE,
    NONNEGATIVE_COUNT,
    NULL,
    PATH,
    TEXT,
    THREADS,
    Rule,
    all_of,
    choice,
    expected,
    is_real,
    is_whole,
    optional,
    real,
    whole,
)
from nerfexp.nerf.appearance import PROTOCOLS
from nerfexp.nerf.hierarchy import HIERARCHIES
from nerfexp.rundir.labels import NOTES, TAGS
from nerfexp.scoring.perceptual import SETTINGS as LPIPS_SETTINGS
from nerfexp.settings.options import options_reading, primary_readers
from nerfexp.training.budgets import AUTO as AUTO_BUDGETS
from nerfexp.training.guard_actions import COLLAPSE_ACTIONS, NONFINITE_ACTIONS

SEED_LIMIT = 2 ** 32  # seeds are whole numbers in [0, 2^32): numpy's and Lightning's range


def registered_choice(fixed: tuple[str, ...], registered: Callable[[], tuple[str, ...]]) -> Rule:
    """One of ``fixed`` or of the names ``registered()`` gives (Lightning's registries), which are read only
    for a value not in ``fixed``: a run with the defaults checks its settings without importing Lightning,
    most of a command's start-up (docs/testing.md)."""
    def values() -> tuple[str, ...]:
        return (*fixed, *registered())
    return (lambda: choice(*values())[0]), lambda v: isinstance(v, str | bool) and (v in fixed or v in values())


def lightning_precisions() -> tuple[str, ...]:
    """The precisions ``lightning.Trainer`` takes by name: the strings of its ``precision`` argument's type (a
    union of literals), read from its public signature."""
    from lightning.pytorch import Trainer

    def literals(hint) -> list:
        return [value for arg in get_args(hint) for value in literals(arg)] if get_args(hint) else [hint]
    return tuple(v for v in literals(get_type_hints(Trainer.__init__)["precision"]) if isinstance(v, str))


def lightning_accelerators() -> tuple[str, ...]:
    from lightning.pytorch.accelerators import AcceleratorRegistry
    return tuple(sorted(AcceleratorRegistry.available_accelerators()))


def lightning_strategies() -> tuple[str, ...]:
    from lightning.pytorch.strategies import StrategyRegistry
    return tuple(StrategyRegistry.available_strategies())


# Adam's eps (added to the gradients' scale) and the weight decay are fractions, as its learning rate
# (``nerfexp.domains.LEARNING_RATE``)
ADAM_EPS = real(0, 1, above=True)
TARGET = ("a dotted Python name (module.Class)", lambda v: isinstance(v, str) and v != "")
BETAS = ("[beta1, beta2], each a finite number in [0, 1)",
         lambda v: isinstance(v, list) and len(v) == 2 and all(is_real(b) and 0 <= b < 1 for b in v))
# devices per node: on a CPU each is a process of its own (trainer=ddp's ddp_spawn starts them all), so at most
# THREAD_LIMIT, more than any machine's CPUs (a GPU count Lightning checks against the GPUs itself)
DEVICES = (f"{expected(THREADS)}, a list of device indices, or auto",
           lambda v: v == "auto" or THREADS[1](v) or (isinstance(v, list) and v != [] and all(map(is_whole, v))))
PLUGINS = ("a list of plugin configs ({_target_: ...}), or null",
           lambda v: v is None or (isinstance(v, list) and all(isinstance(p, dict) and "_target_" in p for p in v)))
# "auto": bf16-mixed where this machine runs bf16 fast, else 32-true (nerfexp.training.precision)
PRECISIONS = registered_choice(("auto",), lightning_precisions)
ACCELERATORS = registered_choice(("auto", "gpu"), lightning_accelerators)
STRATEGIES = registered_choice(("auto",), lightning_strategies)
HIERARCHY = choice(*HIERARCHIES)

# The fractions of training's steps at which the test views are scored too (nerfexp.training.budgets): each strictly
# inside (0, 1), the end being the final test's, in increasing order, so that each names one point of training once;
# or auto (1/4 and 1/2, as many as their cost allows)
TEST_BUDGETS = ("auto, or a list of fractions of the steps, each a finite number > 0 and < 1, strictly increasing "
                "(e.g. [0.25, 0.5]; [] scores the end alone)",
                lambda v: v == AUTO_BUDGETS or isinstance(v, list) and all(is_real(f) and 0 < f < 1 for f in v)
                and all(a < b for a, b in zip(v, v[1:])))

# Every key of the composed config (fnmatch patterns, the first that matches rules), hydra.* aside.
SCHEMA: dict[str, Rule] = {
    "*._target_": TARGET,
    "*._partial_": BOOLEAN,
    "seed": whole(0, SEED_LIMIT - 1),
    "tags": TAGS,  # labels (nerfexp.rundir.labels)
    "notes": NOTES,
    "hierarchical": HIERARCHY,
    "resume": optional(PATH, "train from scratch"),
    # at most THREAD_LIMIT (more than any machine); above the CPUs this process may use: capped at them (nerfexp.cpus)
    "threads": optional(THREADS, "auto: the CPUs this process may use over the jobs run at once"),
    "test_budgets": TEST_BUDGETS,
    # scale: the sizes the groups read, each with the rules of the keys it lands in (readers_rule)
    # the model
    "model.chunk": COUNT,
    "model.compile": BOOLEAN,
    "model.lpips": choice(*LPIPS_SETTINGS),
    "model.lpips_weights": optional(PATH, "the torch hub cache's"),  # and that the file is there (check_lpips)
    "model.lpips_custom": BOOLEAN,  # and that lpips_weights names a file (check_lpips)
    "model.test_protocol": choice(*PROTOCOLS),
    "model.lr_final": LEARNING_RATE,
    "model.lr_warmup_steps": NONNEGATIVE_COUNT,
    "model.optimizer.lr": LEARNING_RATE,
    "model.optimizer.betas": BETAS,
    "model.optimizer.eps": ADAM_EPS,
    "model.optimizer.weight_decay": FRACTION,
    "model.optimizer.fused": BOOLEAN,
    # the components' keys (model.renderer.*, sampler.*, encoding.*, view_dependence.*, proposal.*,
    # acceleration.grid.*, data.*): each class's DOMAINS, beside it (component_rule)
    "datamodule.batch_rays": COUNT,
    "datamodule.seed": whole(0, SEED_LIMIT - 1),
    "acceleration.grid": NULL,  # acceleration=none
    "appearance.embedding": NULL,  # appearance=none
    "appearance.fit": NULL,
    "appearance.test_protocol": choice(*PROTOCOLS),
    "camera_opt.correction": NULL,  # camera_opt=off
    "camera_opt.coarse_to_fine": FRACTION,  # the window it asks of the positional encoding (encoding.position)
    "test_cameras.fit": NULL,  # test_cameras=given
    "datamodule.pose_noise": POSE_NOISE_SETTING,  # degrees in [0, 180], a fraction of the cameras' radius in [0, 1]
    "contraction.function": NULL,  # contraction=none
    # trainer
    "trainer.accelerator": ACCELERATORS,
    "trainer.strategy": STRATEGIES,
    "trainer.devices": DEVICES,
    "trainer.num_nodes": COUNT,
    "trainer.precision": PRECISIONS,
    "trainer.max_steps": COUNT,
    "trainer.val_check_interval": COUNT,
    "trainer.check_val_every_n_epoch": optional(COUNT, "validate by steps"),
    "trainer.num_sanity_val_steps": NONNEGATIVE_COUNT,
    "trainer.log_every_n_steps": COUNT,
    "trainer.default_root_dir": PATH,
    "trainer.enable_progress_bar": BOOLEAN,
    "trainer.enable_model_summary": BOOLEAN,
    "trainer.plugins": PLUGINS,
    # callbacks
    "callbacks.checkpoint.dirpath": PATH,
    "callbacks.checkpoint.save_last": BOOLEAN,
    "callbacks.checkpoint.save_top_k": whole(-1, INTEGER_LIMIT),
    "callbacks.checkpoint.every_n_train_steps": COUNT,
    "callbacks.checkpoint.enable_version_counter": BOOLEAN,
    "callbacks.guard.dirpath": optional(PATH, "no debug files"),
    "callbacks.guard.on_nonfinite": choice(*NONFINITE_ACTIONS),
    "callbacks.guard.max_skips": NONNEGATIVE_COUNT,
    "callbacks.guard.on_collapse": choice(*COLLAPSE_ACTIONS),
    "callbacks.guard.collapse_patience": COUNT,
    "callbacks.guard.collapse_opacity": real(0, 1, above=True),
    # logger
    "logger": NULL,
    "logger.save_dir": PATH,
    "logger.name": TEXT,
    "logger.version": ("a text (empty: none)", lambda v: isinstance(v, str)),
    "logger.experiment_name": TEXT,
    "logger.tracking_uri": TEXT,
    "logger.artifact_location": PATH,
    "logger.project": TEXT,
    "logger.offline": BOOLEAN,
}

# Sections handed to a class as keyword arguments: keys a user adds there (+trainer.gradient_clip_val=1,
# +callbacks.NAME._target_=...) are that class's to check when it is built.
PASSED_ON = ("trainer.*", "callbacks.*", "logger.*", "model.optimizer.*")

# Keys that stand for a whole section of the config through an interpolation (checked where it is set).
REFERENCES = ("datamodule.scene", "model.renderer.field.position_encoding", "model.renderer.field.view_head",
              "view_dependence.direction_encoding", "model.renderer.grid", "model.renderer.sampler", "sampler.proposal",
              "model.renderer.contraction", "model.renderer.appearance", "model.appearance_fit",
              "proposal.network.position_encoding", "model.camera_opt", "model.test_camera_fit")


def matching(patterns, key: str):
    """The first of ``patterns`` that ``key`` matches, or None."""
    return next((p for p in patterns if fnmatchcase(key, p)), None)


# Components whose rules stand in SCHEMA, not beside their class: their modules import Lightning, which a
# command that stops at a bad setting need not wait for (docs/testing.md), or are another library's.
CENTRAL_CLASSES = ("nerfexp.training.", "nerfexp.data.datamodule.", "lightning.", "torch.")


def component_class(target: object) -> type | None:
    """The class a config's ``_target_`` names, where its rules stand beside it (not ``CENTRAL_CLASSES``), else
    None; a target that cannot be imported has none (building it says why)."""
    if not isinstance(target, str) or target.startswith(CENTRAL_CLASSES):
        return None
    try:
        return get_class(target)
    except (ImportError, ValueError):
        return None


def component_rule(cfg: DictConfig, key: str) -> Rule | None:
    """The rule of ``key`` (dotted) declared by the component that takes it as an argument: ``DOMAINS`` of the
    class that the ``_target_`` of ``key``'s section names (``nerfexp.domains``); None where none declares one."""
    section, _, argument = key.rpartition(".")
    node = OmegaConf.select(cfg, section) if section else None
    if not isinstance(node, DictConfig) or "_target_" not in node:
        return None
    return getattr(component_class(node.get("_target_")), "DOMAINS", {}).get(argument)


# The rule of a key that an option of nerfexp's groups reads and nothing in this config does (``scale.lr`` where
# optimizer=ngp sets its own rate): no value of it does anything here, and a user's override of it is refused as
# unused (``nerfexp.settings.unused``), naming the options that read it
UNREAD = ("any value: nothing this config builds reads it", lambda value: True)


def readers_rule(cfg: DictConfig, key: str) -> Rule | None:
    """The rule of ``key`` where other keys of ``cfg`` read it through a plain interpolation (``scale.n_coarse``,
    which ``sampler.n_coarse: ${scale.n_coarse}`` reads): each reader's (``rule_of``: there, the sampler's
    ``DOMAINS``), all of which its value must keep; where a run overrides them all (``model.chunk=100``), those of
    the keys through which nerfexp's own config.yaml reads it (``primary_readers``); ``UNREAD`` where none reads it
    but an option of nerfexp's groups does (``nerfexp.settings.options.options_reading``); None where nothing reads it
    (not a setting)."""
    found = readers(OmegaConf.to_container(cfg, resolve=False)).get(key, []) or list(primary_readers(key))
    rules = [rule for reader in found if reader.split(".")[0] != "hydra" and (rule := rule_of(cfg, reader)) is not None]
    if rules:
        return all_of(*rules)
    return UNREAD if options_reading(key) else None


def rule_of(cfg: DictConfig, key: str) -> Rule | None:
    """``key``'s rule: its component's (``component_rule``), else ``SCHEMA``'s first match, else that of the keys
    that read it (``readers_rule``: the scale's sizes); None: not a setting."""
    if (rule := component_rule(cfg, key)) is not None:
        return rule
    if (pattern := matching(SCHEMA, key)) is not None:
        return SCHEMA[pattern]
    return readers_rule(cfg, key)
