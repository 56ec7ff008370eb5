"""The settings check: ``check_settings`` on the resolved values before anything is built, a bad value
being one line naming the key the user sets (``scale.lr``, not the ``model.optimizer.lr`` it flows into)
and what was expected. Each job is checked once: a single run by the Hydra callback ``SettingsCheck``,
before its directory is made; a sweep's job by ``nerfexp.commands.train`` (Hydra calls no run-start
callback there). Sizes that would not fit in memory are refused with their estimate (``nerfexp.memory``).

The frequency limit comes from ``benchmarks/encoding_precision.py`` (docs/numerics.md): for points of a
scene within |x| < 10 held in float32, features of frequency 2^k pi with k >= 19 are noise. The limit
applies to the frequencies the encoding sees, so an ``input_scale`` below 1 (gamma(s x)) allows larger L.
"""

import math
from collections.abc import Iterator

from hydra.experimental.callback import Callback
from omegaconf import MISSING, DictConfig, OmegaConf

from nerfexp.config_keys import leaves, reference, source_key
from nerfexp.domains import breaks
from nerfexp.errors import ConfigError
from nerfexp.extras import require
from nerfexp.kernels import enabled
from nerfexp.memory import (
    codes_bytes,
    grid_bytes,
    hash_table_bytes,
    network_bytes,
    parameter_bytes,
    require_memory,
    scene_bytes,
)
from nerfexp.settings.rows import check_row
from nerfexp.settings.schema import FLOAT32_TOP_OCTAVE, PASSED_ON, REFERENCES, component_class, matching, rule_of
from nerfexp.settings.unused import check_used, idle_reason
from nerfexp.training.perceptual import check_weights_file


def is_reference(key: str, written: object) -> bool:
    """Whether ``key`` is one of ``REFERENCES`` standing for its section (``written``, its value as the config
    writes it, is a plain interpolation, ``nerfexp.config_keys.reference``): not checked there."""
    return key in REFERENCES and reference(written) is not None


def checked_settings(cfg: DictConfig) -> Iterator[tuple[str, object]]:
    """Each setting of ``cfg`` as the checks see it: (dotted key, resolved value), ``hydra`` and each
    ``REFERENCES`` section aside, which is checked where it is set (``nerfexp.config_keys.leaves``)."""
    return leaves(cfg, skip=is_reference)


def named(cfg: DictConfig, key: str, value) -> str:
    """``KEY=VALUE`` as the user sets it: where ``key``'s value comes from another key through plain
    interpolations (``${scale.lr}``, ``nerfexp.config_keys.source_key``), that key, and which key it
    sets; else ``key`` itself. A text with a character that does not print (a newline) is quoted, escaped."""
    source = source_key(cfg, key)
    value = repr(value) if isinstance(value, str) and not value.isprintable() else value  # one line, as it is
    return f"{key}={value}" if source == key else f"{source}={value} (which sets {key})"


def check_rules(cfg: DictConfig, strict: bool = True) -> None:
    """A ConfigError for the first leaf whose value breaks its rule (its component's ``DOMAINS``, else
    ``SCHEMA``'s: ``nerfexp.settings.schema.rule_of``), or, where ``strict``, that no rule covers. Keys outside
    ``scale`` come first, so that a scale value is named with the key it sets."""
    found = sorted((item for item in checked_settings(cfg) if item[1] is not MISSING),
                   key=lambda item: item[0].startswith("scale."))
    for key, value in found:
        rule = rule_of(cfg, key)
        if rule is None:
            if strict and matching(PASSED_ON, key) is None:
                raise ConfigError(f"{key}={value}: not a setting nerfexp reads "
                                  "(`nerfexp --cfg job` shows those it reads)")
            continue
        if (wanted := breaks(rule, value)) is not None:
            raise ConfigError(f"{named(cfg, key, value)}: expected {wanted}")


def check_frequencies(cfg: DictConfig) -> None:
    """A ConfigError where a positional encoding's top frequency is beyond what float32 positions resolve."""
    for name in ("position", "direction"):
        encoding = OmegaConf.select(cfg, f"encoding.{name}")
        if encoding is None or "n_freqs" not in encoding:
            continue
        key, n_freqs, scale = f"encoding.{name}.n_freqs", encoding.n_freqs, encoding.get("input_scale", 1.0)
        top = n_freqs - 1 + math.log2(scale)  # the octave of the highest frequency the encoding sees
        if n_freqs > 0 and top > FLOAT32_TOP_OCTAVE:
            most = FLOAT32_TOP_OCTAVE + 1 - math.log2(scale)  # >= 1: the rule keeps the scale <= 2^18
            raise ConfigError(f"{key}={n_freqs}: frequencies above 2^{FLOAT32_TOP_OCTAVE} pi are noise for float32 "
                              f"positions (docs/numerics.md); use at most {math.floor(most)} with input_scale "
                              f"{scale:g}")


def check_ray_bounds(cfg: DictConfig) -> None:
    """A ConfigError where the rays' bounds, both set, leave no interval to sample: near must lie before far."""
    near, far = cfg.model.renderer.near, cfg.model.renderer.far
    if near is not None and far is not None and not near < far:
        raise ConfigError(f"{named(cfg, 'model.renderer.near', near)} and {named(cfg, 'model.renderer.far', far)}: "
                          "expected near < far (the rays are sampled between them)")


SAMPLER = "model.renderer.sampler"  # the renderer's sampler (conf/sampler/)


def sampler_networks(cfg: DictConfig, key: str = SAMPLER) -> list[str]:
    """The dotted keys of the networks the renderer's sampler builds (the proposal networks of
    ``hierarchical=proposal``): the sections below ``key`` that name a class (``_target_``) and have a ``depth``,
    where no component on the way leaves them idle (its ``APPLIES``: ``nerfexp.settings.unused.idle_reason``)."""
    node = OmegaConf.select(cfg, key)
    if not isinstance(node, DictConfig) or (key != SAMPLER and idle_reason(cfg, key) is not None):
        return []
    own = [key] if key != SAMPLER and "_target_" in node and "depth" in node else []
    return own + [found for name in node if isinstance(name, str)
                  for found in sampler_networks(cfg, f"{key}.{name}")]


def check_skips(cfg: DictConfig) -> None:
    """A ConfigError where a network's skip connections name a layer it does not have (1..depth-1): the
    field's, and the sampler's networks' (``sampler_networks``)."""
    for key in ["model.renderer.field", *(source_key(cfg, k) for k in sampler_networks(cfg))]:
        network = OmegaConf.select(cfg, key)
        skips = list(network.skips)
        if not all(1 <= s < network.depth for s in skips):
            raise ConfigError(f"{named(cfg, f'{key}.skips', skips)}: layer indices must be in "
                              f"1..{network.depth - 1} for depth {network.depth}")


def sampler_samples(cfg: DictConfig) -> tuple[int, list[str]] | None:
    """The network evaluations per ray of the renderer's sampler, and the keys that set them, as its class says
    (``SAMPLES_PER_RAY``, ``nerfexp.domains``: for the proposals, the rounds' and the field's, counted as the
    field's, an upper bound on their memory); None where its class says nothing."""
    sampler = OmegaConf.select(cfg, SAMPLER)
    counted = getattr(component_class(sampler.get("_target_")), "SAMPLES_PER_RAY", None)
    if counted is None:
        return None
    count, names = counted(OmegaConf.to_container(sampler, resolve=True))
    return count, [f"{SAMPLER}.{name}" for name in names]


def settings_named(cfg: DictConfig, keys: list[str]) -> str:
    """``KEY=VALUE, ...``: each of ``keys`` as the user sets it (``named``)."""
    return ", ".join(named(cfg, key, OmegaConf.select(cfg, key)) for key in keys)


TEST_TIME_FITS = (("model.appearance_fit", "a step of the test images' appearance fit"),
                  ("model.test_camera_fit", "a step of the test cameras' fit"))  # (key, what a step renders)


def check_memory(cfg: DictConfig, training: bool = True) -> None:
    """A ConfigError naming every setting an estimate multiplies (the one a user set among them) where the
    scene, a training batch (where ``training``), an evaluation chunk, a step of a test-time fit (its rays
    rendered with every layer's output kept for the backward pass to the fitted vector, as a training batch's),
    a network's weights, the appearance codes, the hash tables or the occupancy grid would need more than the
    machine's memory (``nerfexp.memory``)."""
    data, field = cfg.data, cfg.model.renderer.field
    if "image_size" in data:
        views = (data.n_train or 0) + data.n_val + data.n_test
        keys = ["data.image_size", *(["data.supersample"] if "supersample" in data else []),
                "data.n_train", "data.n_val", "data.n_test"]
        needed = scene_bytes(views, data.image_size, data.image_size, data.get("supersample", 1))
        require_memory(settings_named(cfg, keys), f"a scene of {views} views of {data.image_size} x "
                       f"{data.image_size} pixels", needed)
    sampled = sampler_samples(cfg)
    hidden = cfg.view_dependence.get("hidden", 0)
    width, width_key = max((field.width, "model.renderer.field.width"), (hidden, "view_dependence.hidden"))
    batches = [("model.chunk", "an evaluation chunk", False)]
    if training:
        batches.insert(0, ("datamodule.batch_rays", "a training batch", True))
    batches += [(f"{key}.rays", what, True) for key, what in TEST_TIME_FITS  # where a fit is set, with its rays
                if OmegaConf.select(cfg, f"{key}.rays") is not None]
    samples, sample_keys = sampled if sampled is not None else (0, [])
    for key, what, kept in batches if sampled is not None else ():
        rays = OmegaConf.select(cfg, key)
        needed = network_bytes(rays, samples, width, field.depth, kept)
        require_memory(settings_named(cfg, [key, *sample_keys, width_key, "model.renderer.field.depth"]),
                       f"{what} of {rays} rays x {samples} samples through {field.depth} layers of {width} units",
                       needed)
    networks = [("model.renderer.field", "a field"), ("view_dependence", "a view head")]
    networks += [(source_key(cfg, key), "a network of the sampler") for key in sampler_networks(cfg)]
    for key, what in networks:
        network = OmegaConf.select(cfg, key)
        size, depth = (network.get("width", network.get("hidden")), network.get("depth", 1))
        if size is not None:
            size_key = f"{key}.width" if "width" in network else f"{key}.hidden"
            keys = [size_key, *([f"{key}.depth"] if "depth" in network else [])]
            require_memory(settings_named(cfg, keys), f"training {what} of {depth} layers of {size} units",
                           parameter_bytes(size, depth))
    embedding = OmegaConf.select(cfg, "model.renderer.appearance")
    if embedding is not None:
        views = data.get("n_train") or 1  # null: every training view of the scene, at least one
        keys = ["model.renderer.appearance.dim", *(["data.n_train"] if "n_train" in data else [])]
        require_memory(settings_named(cfg, keys), f"training the appearance codes of {views} views of "
                       f"{embedding.dim} numbers", codes_bytes(views, embedding.dim))
    position = cfg.encoding.position
    if "log2_table_size" in position:
        needed = hash_table_bytes(position.n_levels, position.log2_table_size, position.features_per_level)
        keys = [f"encoding.position.{key}" for key in ("n_levels", "log2_table_size", "features_per_level")]
        require_memory(settings_named(cfg, keys), f"a hash encoding of {position.n_levels} levels", needed)
    grid = cfg.acceleration.get("grid")
    if grid is not None:
        require_memory(settings_named(cfg, ["acceleration.grid.resolution"]),
                       f"an occupancy grid of {grid.resolution}^3 cells", grid_bytes(grid.resolution))


def check_hash_levels(cfg: DictConfig) -> None:
    """A ConfigError where a hash grid encoding's coarsest resolution is above its finest."""
    position = cfg.encoding.position
    if "coarsest" in position and "finest" in position and position.coarsest > position.finest:
        raise ConfigError(f"{settings_named(cfg, ['encoding.position.coarsest', 'encoding.position.finest'])}: "
                          "expected coarsest <= finest (the levels' resolutions go from one to the other)")


SPARSE_OPTIMIZERS = ("nerfexp.training.optimizers.LazyAdam",)  # take the hash table's sparse gradients


def check_sparse_gradients(cfg: DictConfig) -> None:
    """A ConfigError where the hash table's gradients are sparse and the optimizer is not one of
    ``SPARSE_OPTIMIZERS`` (torch.optim.Adam stops at the first step on a sparse gradient)."""
    if not OmegaConf.select(cfg, "encoding.position.sparse_gradients", default=False):
        return
    target = OmegaConf.select(cfg, "model.optimizer._target_")
    if target not in SPARSE_OPTIMIZERS:
        optimizer = named(cfg, "model.optimizer._target_", target)
        raise ConfigError(f"encoding.position.sparse_gradients=true and {optimizer}: expected an optimizer that "
                          f"takes sparse gradients ({', '.join(SPARSE_OPTIMIZERS)}), or set "
                          "encoding.position.sparse_gradients=false")


def check_contraction(cfg: DictConfig) -> None:
    """A ConfigError where a contraction meets NDC rays (``data.ndc=true``): NDC already maps a forward-facing
    scene's unbounded depth into [0, 1], and a contraction of NDC positions would squeeze nothing."""
    if OmegaConf.select(cfg, "contraction.function") is not None and OmegaConf.select(cfg, "data.ndc", default=False):
        raise ConfigError("contraction=mipnerf360 and data.ndc=true: NDC rays already bound a forward-facing scene's "
                          "depth; set data.ndc=false (with data.near and data.far) to contract world positions, or "
                          "contraction=none")


def check_camera_opt(cfg: DictConfig) -> None:
    """A ConfigError where camera refinement (``model.camera_opt``, or the test cameras' ``model.test_camera_fit``)
    meets NDC rays (``data.ndc=true``): its corrections turn and move world rays, and the loader has made NDC rays
    of them before the module sees them."""
    if OmegaConf.select(cfg, "model.camera_opt") is not None and OmegaConf.select(cfg, "data.ndc", default=False):
        raise ConfigError("camera_opt=so3xr3: the corrections move world rays, and data.ndc=true trains on NDC rays; "
                          "set data.ndc=false (with data.near and data.far) to refine an LLFF scene's cameras")
    if OmegaConf.select(cfg, "model.test_camera_fit") is not None and OmegaConf.select(cfg, "data.ndc", default=False):
        raise ConfigError("test_cameras=refined: the fit turns and moves world rays, and data.ndc=true scores NDC "
                          "rays; set data.ndc=false (with data.near and data.far), or test_cameras=given")


def check_extras(cfg: DictConfig) -> None:
    """A MissingExtraError (a ConfigError) where the config asks for a part of nerfexp whose optional
    package is not installed (``nerfexp.extras``)."""
    if str(OmegaConf.select(cfg, "data._target_", default="")).startswith("nerfexp.data.colmap."):
        require("pycolmap", "data=colmap")
    if OmegaConf.select(cfg, "data.video", default=None, throw_on_missing=False) is not None:
        require("imageio_ffmpeg", "data.video")


def check_lpips(cfg: DictConfig) -> None:
    """A ConfigError where LPIPS must be scored from a weights file that is not there, or not torchvision's
    published one without ``model.lpips_custom`` saying it is the user's own: the one ``model.lpips_weights``
    names, or the torch hub cache's (``nerfexp.training.perceptual.check_weights_file``); the file is read, and
    its SHA-256 taken again, when the model is set up."""
    check_weights_file(OmegaConf.select(cfg, "model.lpips", default=False),
                       OmegaConf.select(cfg, "model.lpips_weights", default=None),
                       OmegaConf.select(cfg, "model.lpips_custom", default=False))


def check_settings(cfg: DictConfig, training: bool = True, scoring: bool = True) -> None:
    """A ConfigError for a ``NERFEXP_KERNELS`` that is not on or off (``nerfexp.kernels.enabled``), a missing
    optional package (first: a component whose package is missing cannot say what its settings are), then the
    first setting that is out of its domain (``check_rules``), a frequency float32 cannot resolve, a skip
    connection past the field's depth, hash grid levels out of order, ray bounds with near not before far,
    sparse gradients without an optimizer that takes them, a size that would not fit in memory, or LPIPS weights
    that must be there and are not (where ``scoring``). ``training``: False for a run read back
    (``check_run_settings``)."""
    missing = sorted(key for key, value in checked_settings(cfg) if value is MISSING)
    if missing:
        raise ConfigError(f"missing mandatory value: {', '.join(missing)} (set it on the command line, "
                          f"e.g. {missing[0]}=...)")
    enabled()  # the kernels' switch, read now so that a value it does not take stops the run before any work
    check_extras(cfg)  # first: a component whose package is missing cannot say what its settings are
    check_rules(cfg, strict=training)
    check_frequencies(cfg)
    check_skips(cfg)
    check_hash_levels(cfg)
    check_ray_bounds(cfg)
    check_sparse_gradients(cfg)
    check_contraction(cfg)
    check_camera_opt(cfg)
    check_memory(cfg, training)
    if scoring:
        check_lpips(cfg)


def check_run_settings(cfg: DictConfig, scoring: bool = False) -> None:
    """``check_settings`` for a run read back (nerfexp-eval, -render, -export, -view): its saved config with the
    user's ``KEY=VALUE`` overrides, checked before anything is built from it, a bad value named as the user set
    it. What only training builds is left out: the keys removed when a run is read back (callbacks, logger,
    ``trainer.default_root_dir``) are not there, and a training batch's memory is not estimated (a run trained
    on a larger machine is read back on a smaller one); a key of a run made by an earlier nerfexp that no rule
    covers is the run's, not a user's mistake, and is passed over. LPIPS's weights are looked for only where
    the command is ``scoring`` the test views (nerfexp-eval): a render needs none."""
    check_settings(cfg, training=False, scoring=scoring)


class SettingsCheck(Callback):
    """Hydra callback (``hydra.callbacks.settings``): ``check_settings`` and ``check_used`` on a single
    run's config before Hydra creates its directory, so that a bad value leaves nothing behind; each job of
    a sweep is checked by ``nerfexp.commands.train`` (the sweep's values differ per job). It stops with
    ``SystemExit``: Hydra turns a callback's exceptions into warnings and goes on."""

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        try:
            check_settings(config)
            check_row(config, config.hydra.runtime.choices, list(config.hydra.overrides.task))
            check_used(config, list(config.hydra.overrides.task))
        except ConfigError as error:
            raise SystemExit(f"nerfexp: error: {error}") from None
