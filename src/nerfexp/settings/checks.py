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
from omegaconf import MISSING, DictConfig, Node, OmegaConf

from nerfexp.config_keys import leaves, source_key
from nerfexp.errors import ConfigError
from nerfexp.extras import require
from nerfexp.memory import hash_table_bytes, network_bytes, require_memory, scene_bytes
from nerfexp.settings.schema import PASSED_ON, REFERENCES, SCHEMA, matching
from nerfexp.settings.unused import check_used
from nerfexp.training.perceptual import check_weights_file

FLOAT32_TOP_OCTAVE = 18  # the largest k of sin(2^k pi x) still meaningful for float32 positions (see above)


def is_reference(key: str, node: Node) -> bool:
    """Whether ``key`` is one of ``REFERENCES`` standing for its section (an interpolation): not checked there."""
    return key in REFERENCES and node._is_interpolation()


def checked_settings(cfg: DictConfig) -> Iterator[tuple[str, object]]:
    """Each setting of ``cfg`` as the checks see it: (dotted key, resolved value), ``hydra`` and each
    ``REFERENCES`` section aside, which is checked where it is set (``nerfexp.config_keys.leaves``)."""
    return leaves(cfg, skip=is_reference)


def named(cfg: DictConfig, key: str, value) -> str:
    """``KEY=VALUE`` as the user sets it: where ``key``'s value comes from another key through plain
    interpolations (``${scale.lr}``, ``nerfexp.config_keys.source_key``), that key, and which key it
    sets; else ``key`` itself."""
    source = source_key(cfg, key)
    return f"{key}={value}" if source == key else f"{source}={value} (which sets {key})"


def check_rules(cfg: DictConfig) -> None:
    """A ConfigError for the first leaf whose value breaks its ``SCHEMA`` rule, or that no rule covers.
    Keys outside ``scale`` come first, so that a scale value is named with the key it sets."""
    found = sorted((item for item in checked_settings(cfg) if item[1] is not MISSING),
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
            raise ConfigError(f"{named(cfg, key, value)}: expected {expected() if callable(expected) else expected}")


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
    """A ConfigError where a network's skip connections name a layer it does not have (1..depth-1): the
    field's, and with ``hierarchical=proposal`` the proposal networks'."""
    networks = {"model.renderer.field": cfg.model.renderer.field}
    if cfg.model.renderer.hierarchical == "proposal":
        networks["proposal.network"] = cfg.proposal.network
    for key, network in networks.items():
        skips = list(network.skips)
        if not all(1 <= s < network.depth for s in skips):
            raise ConfigError(f"{named(cfg, f'{key}.skips', skips)}: layer indices must be in "
                              f"1..{network.depth - 1} for depth {network.depth}")


def samples_per_ray(cfg: DictConfig) -> int:
    """The network evaluations per ray: coarse + (coarse + fine) samples, the single network's, or the
    proposal rounds' and the field's (counted as the field's, an upper bound on their memory)."""
    renderer = cfg.model.renderer
    if renderer.hierarchical == "proposal":
        return sum(cfg.proposal.n_samples) + cfg.proposal.n_final
    return 2 * renderer.n_coarse + renderer.n_fine if renderer.hierarchical else renderer.n_single


def check_memory(cfg: DictConfig) -> None:
    """A ConfigError naming the setting where the scene, a training batch, an evaluation chunk or the hash
    tables would need more than the machine's memory (``nerfexp.memory``)."""
    data, field = cfg.data, cfg.model.renderer.field
    if "image_size" in data:
        views = (data.n_train or 0) + data.n_val + data.n_test
        needed = scene_bytes(views, data.image_size, data.image_size, data.get("supersample", 1))
        require_memory(named(cfg, "data.image_size", data.image_size), f"a scene of {views} views", needed)
    samples = samples_per_ray(cfg)
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


def check_extras(cfg: DictConfig) -> None:
    """A MissingExtraError (a ConfigError) where the config asks for a part of nerfexp whose optional
    package is not installed (``nerfexp.extras``)."""
    if str(OmegaConf.select(cfg, "data._target_", default="")).startswith("nerfexp.data.colmap."):
        require("pycolmap", "data=colmap")
    if OmegaConf.select(cfg, "data.video", default=None, throw_on_missing=False) is not None:
        require("imageio_ffmpeg", "data.video")


def check_lpips(cfg: DictConfig) -> None:
    """A ConfigError where LPIPS must be scored from a weights file that is not there: the one
    ``model.lpips_weights`` names, or under ``model.lpips=true`` the torch hub cache's
    (``nerfexp.training.perceptual.check_weights_file``); the file is read when the model is set up."""
    check_weights_file(OmegaConf.select(cfg, "model.lpips", default=False),
                       OmegaConf.select(cfg, "model.lpips_weights", default=None))


def check_settings(cfg: DictConfig) -> None:
    """A ConfigError for the first setting that is out of its domain (``check_rules``), a frequency
    float32 cannot resolve, a skip connection past the field's depth, ray bounds with near not before far,
    sparse gradients without an optimizer that takes them, a size that would not fit in memory, a missing
    optional package, or LPIPS weights that must be there and are not."""
    missing = sorted(key for key, value in checked_settings(cfg) if value is MISSING)
    if missing:
        raise ConfigError(f"missing mandatory value: {', '.join(missing)} (set it on the command line, "
                          f"e.g. {missing[0]}=...)")
    check_rules(cfg)
    check_frequencies(cfg)
    check_skips(cfg)
    check_ray_bounds(cfg)
    check_sparse_gradients(cfg)
    check_memory(cfg)
    check_extras(cfg)
    check_lpips(cfg)


class SettingsCheck(Callback):
    """Hydra callback (``hydra.callbacks.settings``): ``check_settings`` and ``check_used`` on a single
    run's config before Hydra creates its directory, so that a bad value leaves nothing behind; each job of
    a sweep is checked by ``nerfexp.commands.train`` (the sweep's values differ per job). It stops with
    ``SystemExit``: Hydra turns a callback's exceptions into warnings and goes on."""

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        try:
            check_settings(config)
            check_used(config, list(config.hydra.overrides.task))
        except ConfigError as error:
            raise SystemExit(f"nerfexp: error: {error}") from None
