"""The settings schema: every key of the composed config has a domain here (``SCHEMA``), checked on the
resolved values before anything is built, and a bad value is one line naming the key the user sets
(``scale.lr``, not the ``model.optimizer.lr`` it flows into) and what was expected.

A key nothing in ``SCHEMA`` covers is refused (``+foo=1``: not a setting), so a new key in ``conf/``
cannot ship without a domain (tests/test_settings.py composes every option of every group). Keys a user
adds under a section that a class takes as keyword arguments (``PASSED_ON``: ``+trainer.gradient_clip_val``,
``+callbacks.NAME.*``) are that class's to check; its error is one line too (``nerfexp.train.cli``).
``APPLIES`` lists the keys that do something only with certain other settings: a user's override of one
that does not apply stops a single run (``unused_settings``). Sizes that would not fit in memory are
refused with their estimate (``nerfexp.memory``).

The frequency limit comes from ``benchmarks/encoding_precision.py`` (docs/numerics.md): for points of a
scene within |x| < 10 held in float32, features of frequency 2^k pi with k >= 19 are noise. The limit
applies to the frequencies the encoding sees, so an ``input_scale`` below 1 (gamma(s x)) allows larger L.
"""

import math
from collections.abc import Callable, Iterator
from fnmatch import fnmatchcase
from typing import get_args

from hydra.experimental.callback import Callback
from lightning.fabric.plugins.precision.precision import _PRECISION_INPUT_STR, _PRECISION_INPUT_STR_ALIAS
from lightning.pytorch.accelerators import AcceleratorRegistry
from lightning.pytorch.strategies import StrategyRegistry
from omegaconf import MISSING, DictConfig, ListConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue

from nerfexp.errors import ConfigError
from nerfexp.extras import require
from nerfexp.memory import hash_table_bytes, network_bytes, require_memory, scene_bytes
from nerfexp.nerf.backgrounds import BACKGROUNDS
from nerfexp.nerf.fields import DENSITY_ACTIVATIONS, SH_MAX_DEGREE
from nerfexp.training.guards import COLLAPSE_ACTIONS, NONFINITE_ACTIONS

FLOAT32_TOP_OCTAVE = 18  # the largest k of sin(2^k pi x) still meaningful for float32 positions (see above)
SEED_LIMIT = 2 ** 32  # seeds are whole numbers in [0, 2^32): numpy's and Lightning's range

Rule = tuple[str, Callable[[object], bool]]  # (what is expected, the test)


def is_whole(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def is_real(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def whole(low: int, high: int | None = None) -> Rule:
    """A whole number in [low, high] (high: None for no upper bound)."""
    expected = f"a whole number >= {low}" if high is None else f"a whole number in [{low}, {high}]"
    return expected, lambda v: is_whole(v) and v >= low and (high is None or v <= high)


def real(low: float, high: float | None = None, *, above: bool = False) -> Rule:
    """A finite number >= ``low`` (> ``low`` where ``above``), and <= ``high`` where given."""
    expected = f"a finite number {'>' if above else '>='} {low:g}" + ("" if high is None else f" and <= {high:g}")
    return expected, lambda v: (is_real(v) and (v > low if above else v >= low)
                                and (high is None or v <= high))


def choice(*values) -> Rule:
    return f"one of {', '.join(map(str, values))}", lambda v: isinstance(v, str | bool) and v in values


def optional(rule: Rule, meaning: str) -> Rule:
    """``rule``, or null meaning ``meaning``."""
    return f"{rule[0]}, or null ({meaning})", lambda v: v is None or rule[1](v)


def whole_list(low: int) -> Rule:
    return f"a list of whole numbers >= {low}", lambda v: isinstance(v, list) and all(whole(low)[1](x) for x in v)


COUNT = whole(1)
NONNEGATIVE_COUNT = whole(0)
POSITIVE = real(0, above=True)
FRACTION = real(0, 1)
BOOLEAN = ("true or false", lambda v: isinstance(v, bool))
TEXT = ("a text", lambda v: isinstance(v, str) and v != "")
TARGET = ("a dotted Python name (module.Class)", lambda v: isinstance(v, str) and v != "")
NULL = ("null", lambda v: v is None)
PATH = ("a path", lambda v: isinstance(v, str) and v != "")
BOX = ("[[x0, y0, z0], [x1, y1, z1]] of finite numbers with x0 < x1, y0 < y1, z0 < z1, or null",
       lambda v: v is None or (isinstance(v, list) and len(v) == 2 and all(isinstance(c, list) and len(c) == 3
                                                                         and all(map(is_real, c)) for c in v)
                               and all(a < b for a, b in zip(*v))))
BETAS = ("[beta1, beta2], each a finite number in [0, 1)",
         lambda v: isinstance(v, list) and len(v) == 2 and all(is_real(b) and 0 <= b < 1 for b in v))
DEVICES = ("a whole number >= 1, a list of device indices, or auto",
           lambda v: v == "auto" or COUNT[1](v) or (isinstance(v, list) and v != [] and all(map(is_whole, v))))
PLUGINS = ("a list of plugin configs ({_target_: ...}), or null",
           lambda v: v is None or (isinstance(v, list) and all(isinstance(p, dict) and "_target_" in p for p in v)))
PRECISIONS = choice(*get_args(_PRECISION_INPUT_STR), *get_args(_PRECISION_INPUT_STR_ALIAS))
ACCELERATORS = choice("auto", "gpu", *sorted(AcceleratorRegistry.available_accelerators()))
STRATEGIES = choice("auto", *StrategyRegistry.available_strategies())
SKIPS = whole_list(0)

# Every key of the composed config (fnmatch patterns, the first that matches rules), hydra.* aside.
SCHEMA: dict[str, Rule] = {
    "*._target_": TARGET,
    "*._partial_": BOOLEAN,
    "seed": whole(0, SEED_LIMIT - 1),
    "hierarchical": BOOLEAN,
    "resume": optional(PATH, "train from scratch"),
    # scale: the sizes the groups read (each checked again where it lands)
    "scale.steps": COUNT,
    "scale.lr": POSITIVE,
    "scale.lr_final": POSITIVE,
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
    "scale.position_input_scale": POSITIVE,
    "scale.max_side": optional(COUNT, "never shrink"),
    "scale.test_stride": COUNT,
    "scale.hash_log2_table_size": whole(1, 62),
    "scale.hash_finest": COUNT,
    # the model
    "model.chunk": COUNT,
    "model.compile": BOOLEAN,
    "model.lr_final": POSITIVE,
    "model.lr_warmup_steps": NONNEGATIVE_COUNT,
    "model.optimizer.lr": POSITIVE,
    "model.optimizer.betas": BETAS,
    "model.optimizer.eps": POSITIVE,
    "model.optimizer.weight_decay": real(0),
    "model.renderer.hierarchical": BOOLEAN,
    "model.renderer.n_coarse": COUNT,
    "model.renderer.n_fine": COUNT,
    "model.renderer.n_single": COUNT,
    "model.renderer.near": optional(real(0), "from the scene"),
    "model.renderer.far": optional(POSITIVE, "from the scene"),
    "model.renderer.background": choice(*BACKGROUNDS),
    "model.renderer.field.depth": COUNT,
    "model.renderer.field.width": COUNT,
    "model.renderer.field.skips": SKIPS,
    "model.renderer.field.density_activation": choice(*DENSITY_ACTIVATIONS),
    "model.renderer.field.density_bias": real(-math.inf, above=True),
    "model.renderer.field.density_noise_std": real(0),
    # encodings and view dependence
    "encoding.*.n_freqs": NONNEGATIVE_COUNT,  # and the float32 limit (check_frequencies)
    "encoding.*.input_scale": POSITIVE,
    "encoding.position.n_levels": COUNT,
    "encoding.position.features_per_level": COUNT,
    "encoding.position.log2_table_size": whole(1, 62),
    "encoding.position.coarsest": COUNT,
    "encoding.position.finest": COUNT,
    "encoding.position.include_input": BOOLEAN,
    "view_dependence.degree": whole(0, SH_MAX_DEGREE),
    "view_dependence.hidden": COUNT,
    # data
    "data.root": PATH,
    "data.video": optional(PATH, "the photographs in images/"),
    "data.fps": POSITIVE,
    "data.image_size": COUNT,
    "data.supersample": COUNT,
    "data.downscale": COUNT,
    "data.factor": COUNT,
    "data.max_side": optional(COUNT, "never shrink"),
    "data.n_train": optional(COUNT, "all"),
    "data.n_val": COUNT,
    "data.n_test": COUNT,
    "data.test_stride": COUNT,
    "data.holdout": whole(2),
    "data.ndc": BOOLEAN,
    "data.bound": POSITIVE,
    "data.near": optional(real(0), "from the scene"),
    "data.far": optional(POSITIVE, "from the scene"),
    "data.background": choice(*BACKGROUNDS),
    "data.aabb": BOX,
    "data.camera_model": TEXT,  # COLMAP's model names (checked against pycolmap's list when it runs)
    "data.matcher": optional(choice("exhaustive", "sequential"), "sequential for a video, else exhaustive"),
    "data.max_features": COUNT,
    "data.threads": ("-1 (every core) or a whole number >= 1", lambda v: v == -1 or COUNT[1](v)),
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
    "callbacks.checkpoint.save_top_k": whole(-1),
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
              "view_dependence.direction_encoding", "model.renderer.grid")


def hierarchical_only(cfg: DictConfig) -> str | None:
    return None if cfg.hierarchical else ("hierarchical=false (one network of model.renderer.n_single samples; "
                                          "set scale.n_single)")


def single_only(cfg: DictConfig) -> str | None:
    return None if not cfg.hierarchical else ("hierarchical=true (a coarse network of model.renderer.n_coarse "
                                              "samples and a fine one of n_coarse + n_fine; set scale.n_coarse "
                                              "and scale.n_fine)")


def needs(section: str, key: str, group: str) -> Callable[[DictConfig], str | None]:
    """The reason a key is unused unless ``section`` has ``key``: the choice of ``group`` made it absent."""
    def reason(cfg: DictConfig) -> str | None:
        node = OmegaConf.select(cfg, section)
        return None if isinstance(node, DictConfig) and key in node else f"this {group} (it has no {section}.{key})"
    return reason


def video_only(cfg: DictConfig) -> str | None:
    return None if OmegaConf.select(cfg, "data.video") is not None else "data.video=null (photographs, not a video)"


def boxed(cfg: DictConfig) -> str | None:
    uses = OmegaConf.select(cfg, "acceleration.grid") is not None or "log2_table_size" in cfg.encoding.position
    return None if uses else "acceleration=none and encoding other than hashgrid (nothing reads the box)"


# Keys that do something only with certain other settings: key pattern -> why it is unused (None: it is used).
APPLIES: dict[str, Callable[[DictConfig], str | None]] = {
    "scale.n_coarse": hierarchical_only,
    "scale.n_fine": hierarchical_only,
    "model.renderer.n_coarse": hierarchical_only,
    "model.renderer.n_fine": hierarchical_only,
    "scale.n_single": single_only,
    "model.renderer.n_single": single_only,
    "scale.view_hidden": needs("view_dependence", "hidden", "view_dependence"),
    "scale.position_input_scale": needs("encoding.position", "input_scale", "encoding"),
    "scale.hash_*": needs("encoding.position", "log2_table_size", "encoding"),
    "scale.image_size": needs("data", "image_size", "data"),
    "scale.max_side": needs("data", "max_side", "data"),
    "scale.test_stride": needs("data", "test_stride", "data"),
    "data.fps": video_only,
    "data.aabb": boxed,
}


def matching(patterns, key: str):
    """The first of ``patterns`` that ``key`` matches, or None."""
    return next((p for p in patterns if fnmatchcase(key, p)), None)


def leaves(cfg: DictConfig, prefix: str = "") -> Iterator[tuple[str, object]]:
    """Each leaf of ``cfg`` as (dotted key, resolved value), ``hydra`` and ``REFERENCES`` aside; a value
    made from Hydra's runtime (``${hydra:runtime.output_dir}/...``) is given unresolved (a path)."""
    for name in cfg.keys():
        key = f"{prefix}{name}"
        node = cfg._get_node(name)
        if key == "hydra" or (key in REFERENCES and OmegaConf.is_interpolation(cfg, name)):
            continue
        raw = node._value()
        if isinstance(raw, str) and "${hydra:" in raw:
            yield key, raw
        elif isinstance(node, DictConfig) and not node._is_none():
            yield from leaves(node, f"{key}.")
        elif node._is_missing():
            yield key, MISSING
        else:
            try:
                value = cfg[name]
            except MissingMandatoryValue:  # an interpolation of a missing value: that key is reported
                continue
            yield key, OmegaConf.to_container(value, resolve=True) if isinstance(value, ListConfig) else value


def named(cfg: DictConfig, key: str, value) -> str:
    """``KEY=VALUE`` as the user sets it: where ``key``'s value is a plain interpolation (``${scale.lr}``),
    the key it names, and which key it sets; else ``key`` itself."""
    parent, _, leaf = key.rpartition(".")
    node = (OmegaConf.select(cfg, parent) if parent else cfg)._get_node(leaf)
    raw = node._value() if node is not None else None
    if isinstance(raw, str) and raw.startswith("${") and raw.endswith("}") and raw.count("$") == 1 and ":" not in raw:
        return f"{raw[2:-1]}={value} (which sets {key})"
    return f"{key}={value}"


def check_rules(cfg: DictConfig) -> None:
    """A ConfigError for the first leaf whose value breaks its ``SCHEMA`` rule, or that no rule covers.
    Keys outside ``scale`` come first, so that a scale value is named with the key it sets."""
    found = sorted((item for item in leaves(cfg) if item[1] is not MISSING),
                   key=lambda item: item[0].startswith("scale."))
    for key, value in found:
        pattern = matching(SCHEMA, key)
        if pattern is None:
            if matching(PASSED_ON, key) is None:
                raise ConfigError(f"{key}={value}: not a setting nerfexp reads "
                                  "(`nerfexp --cfg job` shows those it reads)")
            continue
        expected, valid = SCHEMA[pattern]
        if not valid(value):
            raise ConfigError(f"{named(cfg, key, value)}: expected {expected}")


def check_frequencies(cfg: DictConfig) -> None:
    """A ConfigError where a positional encoding's top frequency is beyond what float32 positions resolve."""
    for name in ("position", "direction"):
        encoding = OmegaConf.select(cfg, f"encoding.{name}")
        if encoding is None or "n_freqs" not in encoding:
            continue
        key, n_freqs, scale = f"encoding.{name}.n_freqs", encoding.n_freqs, encoding.get("input_scale", 1.0)
        top = n_freqs - 1 + math.log2(scale)  # the octave of the highest frequency the encoding sees
        if n_freqs > 0 and top > FLOAT32_TOP_OCTAVE:
            most = FLOAT32_TOP_OCTAVE + 1 - math.log2(scale)
            if most < 1:  # the scale alone puts the lowest frequency past the limit
                raise ConfigError(f"{named(cfg, f'encoding.{name}.input_scale', scale)}: frequencies above "
                                  f"2^{FLOAT32_TOP_OCTAVE} pi are noise for float32 positions (docs/numerics.md); "
                                  f"use at most 2^{FLOAT32_TOP_OCTAVE}")
            raise ConfigError(f"{key}={n_freqs}: frequencies above 2^{FLOAT32_TOP_OCTAVE} pi are noise for float32 "
                              f"positions (docs/numerics.md); use at most {math.floor(most)} with input_scale "
                              f"{scale:g}")


def check_ray_bounds(cfg: DictConfig) -> None:
    """A ConfigError where the rays' bounds, both set, leave no interval to sample: near must lie before far."""
    near, far = cfg.model.renderer.near, cfg.model.renderer.far
    if near is not None and far is not None and not near < far:
        raise ConfigError(f"{named(cfg, 'model.renderer.near', near)} and {named(cfg, 'model.renderer.far', far)}: "
                          "expected near < far (the rays are sampled between them)")


def check_skips(cfg: DictConfig) -> None:
    """A ConfigError where the field's skip connections name a layer it does not have (1..depth-1)."""
    field = cfg.model.renderer.field
    skips = list(field.skips)
    if not all(1 <= s < field.depth for s in skips):
        raise ConfigError(f"{named(cfg, 'model.renderer.field.skips', skips)}: layer indices must be in "
                          f"1..{field.depth - 1} for depth {field.depth}")


def samples_per_ray(renderer: DictConfig) -> int:
    """The network evaluations per ray: coarse + (coarse + fine) samples, or the single network's."""
    return 2 * renderer.n_coarse + renderer.n_fine if renderer.hierarchical else renderer.n_single


def check_memory(cfg: DictConfig) -> None:
    """A ConfigError naming the setting where the scene, a training batch, an evaluation chunk or the hash
    tables would need more than the machine's memory (``nerfexp.memory``)."""
    data, renderer, field = cfg.data, cfg.model.renderer, cfg.model.renderer.field
    if "image_size" in data:
        views = (data.n_train or 0) + data.n_val + data.n_test
        needed = scene_bytes(views, data.image_size, data.image_size, data.get("supersample", 1))
        require_memory(named(cfg, "data.image_size", data.image_size), f"a scene of {views} views", needed)
    samples = samples_per_ray(renderer)
    width = max(field.width, cfg.view_dependence.get("hidden", 0))
    for key, rays, what, training in (("datamodule.batch_rays", cfg.datamodule.batch_rays, "a training batch", True),
                                      ("model.chunk", cfg.model.chunk, "an evaluation chunk", False)):
        needed = network_bytes(rays, samples, width, field.depth, training)
        require_memory(named(cfg, key, rays), f"{what} of {rays} rays x {samples} samples", needed)
    position = cfg.encoding.position
    if "log2_table_size" in position:
        needed = hash_table_bytes(position.n_levels, position.log2_table_size, position.features_per_level)
        require_memory(named(cfg, "encoding.position.log2_table_size", position.log2_table_size),
                       f"hash tables of {position.n_levels} levels", needed)


def check_extras(cfg: DictConfig) -> None:
    """A MissingExtraError (a ConfigError) where the config asks for a part of nerfexp whose optional
    package is not installed (``nerfexp.extras``)."""
    if str(OmegaConf.select(cfg, "data._target_", default="")).startswith("nerfexp.data.colmap."):
        require("pycolmap", "data=colmap")
    if OmegaConf.select(cfg, "data.video", default=None, throw_on_missing=False) is not None:
        require("imageio_ffmpeg", "data.video")


def check_settings(cfg: DictConfig) -> None:
    """A ConfigError for the first setting that is out of its domain (``check_rules``), a frequency
    float32 cannot resolve, a skip connection past the field's depth, ray bounds with near not before far,
    a size that would not fit in memory, or a missing optional package."""
    missing = sorted(key for key, value in leaves(cfg) if value is MISSING)
    if missing:
        raise ConfigError(f"missing mandatory value: {', '.join(missing)} (set it on the command line, "
                          f"e.g. {missing[0]}=...)")
    check_rules(cfg)
    check_frequencies(cfg)
    check_skips(cfg)
    check_ray_bounds(cfg)
    check_memory(cfg)
    check_extras(cfg)


def overridden_key(override: str) -> str:
    """The key of a Hydra override (``+scale.n_fine=64`` -> ``scale.n_fine``)."""
    return override.split("=", 1)[0].lstrip("+~")


def unused_settings(cfg: DictConfig, overrides: list[str]) -> list[tuple[str, str]]:
    """The ``overrides`` a user gave whose key does nothing with the rest of ``cfg`` (``APPLIES``), each
    with the reason: [(override, reason)]. Defaults the user did not set are never listed."""
    unused = []
    for override in overrides:
        pattern = matching(APPLIES, overridden_key(override))
        reason = APPLIES[pattern](cfg) if pattern else None
        if reason:
            unused.append((override, reason))
    return unused


def without_unused(cfg: DictConfig, resolved: dict, overrides: list[str]) -> dict:
    """``resolved`` (``cfg`` resolved, as a run records it) with null for each key of ``overrides`` (unused
    settings of a sweep's job, ``unused_settings``) and for each key that is a plain interpolation of one
    (``model.renderer.n_fine: ${scale.n_fine}``): the record says what the run used, not what was asked."""
    keys = {overridden_key(o) for o in overrides}
    keys |= {key for key, raw in raw_leaves(cfg) if isinstance(raw, str) and raw[2:-1] in keys and raw.startswith("${")}
    recorded = OmegaConf.create(resolved)
    for key in keys:
        OmegaConf.update(recorded, key, None, force_add=False)
    return OmegaConf.to_container(recorded)


def raw_leaves(cfg: DictConfig, prefix: str = "") -> Iterator[tuple[str, object]]:
    """Each leaf of ``cfg`` as (dotted key, its unresolved value), ``hydra`` aside."""
    for name in cfg.keys():
        node, key = cfg._get_node(name), f"{prefix}{name}"
        if key != "hydra" and isinstance(node, DictConfig) and not node._is_none() and not node._is_interpolation():
            yield from raw_leaves(node, f"{key}.")
        elif key != "hydra":
            yield key, node._value()


def check_used(cfg: DictConfig, overrides: list[str]) -> None:
    """A ConfigError for the first of ``overrides`` that does nothing (``unused_settings``)."""
    for override, reason in unused_settings(cfg, overrides)[:1]:
        raise ConfigError(f"{override}: not used with {reason}")


class SettingsCheck(Callback):
    """Hydra callback (``hydra.callbacks.settings``): ``check_settings`` and ``check_used`` on a single
    run's config before Hydra creates its directory, so that a bad value leaves nothing behind; each job of
    a sweep is checked by ``nerfexp.train`` (the sweep's values differ per job). It stops with
    ``SystemExit``: Hydra turns a callback's exceptions into warnings and goes on."""

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        try:
            check_settings(config)
            check_used(config, list(config.hydra.overrides.task))
        except ConfigError as error:
            raise SystemExit(f"nerfexp: error: {error}") from None
