"""The settings' domains: every key of the composed config has one in ``SCHEMA`` (fnmatch patterns, the
first that matches rules), a rule being what is expected, in words for the error, and the test.

A key nothing in ``SCHEMA`` covers is not a setting, so a new key in ``conf/`` cannot ship without a domain
(tests/test_settings.py composes every option of every group). Keys a user adds under a section that a
class takes as keyword arguments (``PASSED_ON``: ``+trainer.gradient_clip_val``, ``+callbacks.NAME.*``)
are that class's to check; its error is one line too (``nerfexp.commands.train.cli``). The domains are
read from the components' own constants (backgrounds, activations, the guards' actions, Lightning's
registries), so that a new choice there is a valid setting here.
"""

import math
from collections.abc import Callable
from fnmatch import fnmatchcase
from typing import get_args

import torch

from nerfexp.data.video import FPS_RANGE
from nerfexp.geometry.cameras import POSITION_LIMIT
from nerfexp.nerf.backgrounds import BACKGROUNDS
from nerfexp.nerf.encodings import HASH_MAX_LOG2_TABLE_SIZE, HASH_RESOLUTION_LIMIT
from nerfexp.nerf.fields import DENSITY_ACTIVATIONS, SH_MAX_DEGREE
from nerfexp.nerf.volume_renderer import HIERARCHIES
from nerfexp.training.guard_actions import COLLAPSE_ACTIONS, NONFINITE_ACTIONS
from nerfexp.training.perceptual import SETTINGS as LPIPS_SETTINGS

SEED_LIMIT = 2 ** 32  # seeds are whole numbers in [0, 2^32): numpy's and Lightning's range
# Counts (steps, rays, samples, units, views, ...) at most 2^63 - 1: torch and numpy hold whole numbers, and the
# loggers their steps, in 64-bit integers. Counts that size arrays are bounded by the memory estimates too
# (nerfexp.settings.checks.check_memory), and COLMAP's by its C ints.
INTEGER_LIMIT = 2 ** 63 - 1
C_INT_LIMIT = 2 ** 31 - 1
FLOAT32_TOP_OCTAVE = 18  # the largest k of sin(2^k pi x) still meaningful for float32 positions (checks.py)
# Offsets of a raw density or roughness (a bias, noise) within +-88: exp and softplus of the raw value stay finite
# float32 numbers (exp overflows float32 past log of its largest value, 88.7...)
RAW_LIMIT = math.floor(math.log(torch.finfo(torch.float32).max))
# A loss term's weight at most 2^24: weighted more, the colour loss (about 1 at most) falls below float32's
# resolution of their sum, and training ignores the images
LOSS_WEIGHT_LIMIT = 2.0 ** 24

# (what is expected, the test); what is expected may be a function that says it, where saying it is dear
Rule = tuple[str | Callable[[], str], Callable[[object], bool]]


def is_whole(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def is_real(value) -> bool:
    """A finite number (a whole number of any size is one: it is never converted to a float to be tested)."""
    return isinstance(value, int | float) and not isinstance(value, bool) and (isinstance(value, int)
                                                                             or math.isfinite(value))


def is_position(value) -> bool:
    """A coordinate in scene units within ``POSITION_LIMIT`` of 0."""
    return is_real(value) and abs(value) <= POSITION_LIMIT


def is_power_of_two(value: float) -> bool:
    return value > 0 and float(value).is_integer() and int(value) & (int(value) - 1) == 0


def bound_text(value: float) -> str:
    """A bound as a rule says it: a power of two from 2^20 on as ``2^24``, one less than a power of two
    past 2^32 as ``2^63 - 1``, a whole number in full, another number as ``{:g}`` does."""
    if abs(value) >= 2 ** 20 and is_power_of_two(abs(value)):
        return f"{'-' if value < 0 else ''}2^{int(abs(value)).bit_length() - 1}"
    if value > 2 ** 32 and is_power_of_two(value + 1):
        return f"2^{int(value + 1).bit_length() - 1} - 1"
    return str(value) if isinstance(value, int) else f"{value:g}"


def whole(low: int, high: int | None = None) -> Rule:
    """A whole number in [low, high] (high: None for no upper bound)."""
    expected = f"a whole number >= {low}" if high is None else f"a whole number in [{low}, {bound_text(high)}]"
    return expected, lambda v: is_whole(v) and v >= low and (high is None or v <= high)


def real(low: float, high: float | None = None, *, above: bool = False) -> Rule:
    """A finite number >= ``low`` (> ``low`` where ``above``), and <= ``high`` where given."""
    expected = (f"a finite number {'>' if above else '>='} {bound_text(low)}"
                + ("" if high is None else f" and <= {bound_text(high)}"))
    return expected, lambda v: (is_real(v) and (v > low if above else v >= low)
                                and (high is None or v <= high))


def yaml_word(value) -> str:
    """``value`` as a config writes it: true and false for booleans."""
    return str(value).lower() if isinstance(value, bool) else str(value)


def choice(*values) -> Rule:
    """One of ``values`` (strings or booleans: 1 and 0, equal to True and False, are neither)."""
    return f"one of {', '.join(map(yaml_word, values))}", lambda v: isinstance(v, str | bool) and v in values


def registered_choice(fixed: tuple[str, ...], registered: Callable[[], tuple[str, ...]]) -> Rule:
    """One of ``fixed`` or of the names ``registered()`` gives (Lightning's registries), which are read only
    for a value not in ``fixed``: a run with the defaults checks its settings without importing Lightning,
    most of a command's start-up (docs/testing.md)."""
    def values() -> tuple[str, ...]:
        return (*fixed, *registered())
    return (lambda: choice(*values())[0]), lambda v: isinstance(v, str | bool) and (v in fixed or v in values())


def lightning_precisions() -> tuple[str, ...]:
    from lightning.fabric.plugins.precision.precision import _PRECISION_INPUT_STR, _PRECISION_INPUT_STR_ALIAS
    return (*get_args(_PRECISION_INPUT_STR), *get_args(_PRECISION_INPUT_STR_ALIAS))


def lightning_accelerators() -> tuple[str, ...]:
    from lightning.pytorch.accelerators import AcceleratorRegistry
    return tuple(sorted(AcceleratorRegistry.available_accelerators()))


def lightning_strategies() -> tuple[str, ...]:
    from lightning.pytorch.strategies import StrategyRegistry
    return tuple(StrategyRegistry.available_strategies())


def optional(rule: Rule, meaning: str) -> Rule:
    """``rule``, or null meaning ``meaning``."""
    return f"{rule[0]}, or null ({meaning})", lambda v: v is None or rule[1](v)


def whole_list(low: int) -> Rule:
    return f"a list of whole numbers >= {low}", lambda v: isinstance(v, list) and all(whole(low)[1](x) for x in v)


COUNT = whole(1, INTEGER_LIMIT)
NONNEGATIVE_COUNT = whole(0, INTEGER_LIMIT)
COLMAP_COUNT = whole(1, C_INT_LIMIT)
FRACTION = real(0, 1)
# Adam moves each weight by about the learning rate per step: above 1 a step outweighs the weights themselves
# (initialised within +-1); its eps (added to the gradients' scale) and the weight decay are fractions too
LEARNING_RATE = real(0, 1, above=True)
ADAM_EPS = real(0, 1, above=True)
NEAR = real(0, POSITION_LIMIT)  # distances along rays, in scene units (geometry.cameras.POSITION_LIMIT)
FAR = real(0, POSITION_LIMIT, above=True)
RAW_OFFSET = real(-RAW_LIMIT, RAW_LIMIT)
LOSS_WEIGHT = real(0, LOSS_WEIGHT_LIMIT)
# gamma(s x): a scale above 2^18 puts even the lowest frequency past float32's (and with n_freqs, check_frequencies)
INPUT_SCALE = real(0, 2.0 ** FLOAT32_TOP_OCTAVE, above=True)
FPS = real(*FPS_RANGE)  # data.video's frames kept per second (nerfexp.data.video.FPS_RANGE)
BOOLEAN = ("true or false", lambda v: isinstance(v, bool))
TEXT = ("a text", lambda v: isinstance(v, str) and v != "")
TARGET = ("a dotted Python name (module.Class)", lambda v: isinstance(v, str) and v != "")
NULL = ("null", lambda v: v is None)
PATH = ("a path", lambda v: isinstance(v, str) and v != "")
BOX = ("[[x0, y0, z0], [x1, y1, z1]] of numbers within +-2^24 with x0 < x1, y0 < y1, z0 < z1, or null",
       lambda v: v is None or (isinstance(v, list) and len(v) == 2 and all(isinstance(c, list) and len(c) == 3
                                                                         and all(map(is_position, c)) for c in v)
                               and all(a < b for a, b in zip(*v))))
BETAS = ("[beta1, beta2], each a finite number in [0, 1)",
         lambda v: isinstance(v, list) and len(v) == 2 and all(is_real(b) and 0 <= b < 1 for b in v))
DEVICES = ("a whole number >= 1, a list of device indices, or auto",
           lambda v: v == "auto" or COUNT[1](v) or (isinstance(v, list) and v != [] and all(map(is_whole, v))))
PLUGINS = ("a list of plugin configs ({_target_: ...}), or null",
           lambda v: v is None or (isinstance(v, list) and all(isinstance(p, dict) and "_target_" in p for p in v)))
# "auto": bf16-mixed where this machine runs bf16 fast, else 32-true (nerfexp.training.precision)
PRECISIONS = registered_choice(("auto",), lightning_precisions)
ACCELERATORS = registered_choice(("auto", "gpu"), lightning_accelerators)
STRATEGIES = registered_choice(("auto",), lightning_strategies)
SKIPS = whole_list(0)
HIERARCHY = choice(*HIERARCHIES)

# Every key of the composed config (fnmatch patterns, the first that matches rules), hydra.* aside.
SCHEMA: dict[str, Rule] = {
    "*._target_": TARGET,
    "*._partial_": BOOLEAN,
    "seed": whole(0, SEED_LIMIT - 1),
    "hierarchical": HIERARCHY,
    "resume": optional(PATH, "train from scratch"),
    # scale: the sizes the groups read (each checked again where it lands)
    "scale.steps": COUNT,
    "scale.lr": LEARNING_RATE,
    "scale.lr_final": LEARNING_RATE,
    "scale.lr_warmup_steps": NONNEGATIVE_COUNT,
    "scale.batch_rays": COUNT,
    "scale.depth": COUNT,
    "scale.width": COUNT,
    "scale.skips": SKIPS,
    "scale.view_hidden": COUNT,
    "scale.n_coarse": COUNT,
    "scale.n_fine": COUNT,
    "scale.n_single": COUNT,
    "scale.chunk": COUNT,
    "scale.val_every": COUNT,
    "scale.image_size": COUNT,
    "scale.position_input_scale": INPUT_SCALE,
    "scale.max_side": optional(COUNT, "never shrink"),
    "scale.test_stride": COUNT,
    "scale.hash_log2_table_size": whole(1, HASH_MAX_LOG2_TABLE_SIZE),
    "scale.hash_finest": whole(1, HASH_RESOLUTION_LIMIT - 1),
    # the model
    "model.chunk": COUNT,
    "model.compile": BOOLEAN,
    "model.lpips": choice(*LPIPS_SETTINGS),
    "model.lpips_weights": optional(PATH, "the torch hub cache's"),  # and that the file is there (check_lpips)
    "model.lr_final": LEARNING_RATE,
    "model.lr_warmup_steps": NONNEGATIVE_COUNT,
    "model.optimizer.lr": LEARNING_RATE,
    "model.optimizer.betas": BETAS,
    "model.optimizer.eps": ADAM_EPS,
    "model.optimizer.weight_decay": FRACTION,
    "model.optimizer.fused": BOOLEAN,
    "model.renderer.hierarchical": HIERARCHY,
    "model.renderer.n_coarse": COUNT,
    "model.renderer.n_fine": COUNT,
    "model.renderer.n_single": COUNT,
    "model.renderer.near": optional(NEAR, "from the scene"),
    "model.renderer.far": optional(FAR, "from the scene"),
    "model.renderer.background": choice(*BACKGROUNDS),
    "model.renderer.field.depth": COUNT,
    "model.renderer.field.width": COUNT,
    "model.renderer.field.skips": SKIPS,
    "model.renderer.field.density_activation": choice(*DENSITY_ACTIVATIONS),
    "model.renderer.field.density_bias": RAW_OFFSET,
    "model.renderer.field.density_noise_std": real(0, RAW_LIMIT),
    "proposal.network.depth": COUNT,
    "proposal.network.width": COUNT,
    "proposal.network.skips": SKIPS,
    "proposal.network.density_activation": choice(*DENSITY_ACTIVATIONS),
    "proposal.network.density_bias": RAW_OFFSET,
    "proposal.n_samples": ("a non-empty list of sample counts, each a whole number >= 1",
                           lambda v: isinstance(v, list) and v != [] and all(COUNT[1](n) for n in v)),
    "proposal.n_final": COUNT,
    "proposal.interlevel_weight": real(0, LOSS_WEIGHT_LIMIT, above=True),  # it alone trains the proposal networks
    "proposal.distortion_weight": LOSS_WEIGHT,
    # encodings and view dependence
    "encoding.*.n_freqs": NONNEGATIVE_COUNT,  # and the float32 limit (check_frequencies)
    "encoding.*.input_scale": INPUT_SCALE,
    "encoding.position.n_levels": COUNT,
    "encoding.position.features_per_level": COUNT,
    "encoding.position.log2_table_size": whole(1, HASH_MAX_LOG2_TABLE_SIZE),
    "encoding.position.coarsest": whole(1, HASH_RESOLUTION_LIMIT - 1),  # and <= finest (check_hash_levels)
    "encoding.position.finest": whole(1, HASH_RESOLUTION_LIMIT - 1),
    "encoding.position.include_input": BOOLEAN,
    "encoding.position.sparse_gradients": BOOLEAN,  # and an optimizer that takes them (check_sparse_gradients)
    "view_dependence.degree": whole(0, SH_MAX_DEGREE),
    "view_dependence.hidden": COUNT,
    "view_dependence.n_levels": whole(1, 6),  # bands up to l = 32, where the float32 basis is still accurate
    "view_dependence.roughness_bias": RAW_OFFSET,
    "view_dependence.normal_weight": LOSS_WEIGHT,
    "view_dependence.orientation_weight": LOSS_WEIGHT,
    # data
    "data.root": PATH,
    "data.video": optional(PATH, "the photographs in images/"),
    "data.fps": FPS,
    "data.image_size": COUNT,
    "data.supersample": COUNT,
    "data.downscale": COUNT,
    "data.factor": COUNT,
    "data.max_side": optional(COUNT, "never shrink"),
    "data.n_train": optional(COUNT, "all"),
    "data.n_val": COUNT,
    "data.n_test": COUNT,
    "data.test_stride": COUNT,
    "data.holdout": whole(2, INTEGER_LIMIT),
    "data.ndc": BOOLEAN,
    "data.bound": FAR,
    "data.near": optional(NEAR, "from the scene"),
    "data.far": optional(FAR, "from the scene"),
    "data.background": choice(*BACKGROUNDS),
    "data.aabb": BOX,
    "data.camera_model": TEXT,  # COLMAP's model names (checked against pycolmap's list when it runs)
    "data.matcher": optional(choice("exhaustive", "sequential"), "sequential for a video, else exhaustive"),
    "data.max_features": COLMAP_COUNT,
    "data.threads": (f"-1 (every core) or {COLMAP_COUNT[0]}", lambda v: v == -1 or COLMAP_COUNT[1](v)),
    "data.min_registered": real(0, 1, above=True),
    "data.verbose": BOOLEAN,
    "datamodule.batch_rays": COUNT,
    "datamodule.seed": whole(0, SEED_LIMIT - 1),
    # acceleration
    "acceleration.grid": NULL,
    "acceleration.grid.resolution": COUNT,
    "acceleration.grid.threshold": real(0, 1, above=True),
    "acceleration.grid.decay": FRACTION,
    "acceleration.grid.warmup_steps": NONNEGATIVE_COUNT,
    "acceleration.grid.update_every": COUNT,
    "acceleration.grid.early_stop_transmittance": real(0, 1),
    "acceleration.grid.segments": COUNT,
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
              "view_dependence.direction_encoding", "model.renderer.grid", "model.renderer.proposal",
              "proposal.network.position_encoding")


def matching(patterns, key: str):
    """The first of ``patterns`` that ``key`` matches, or None."""
    return next((p for p in patterns if fnmatchcase(key, p)), None)
