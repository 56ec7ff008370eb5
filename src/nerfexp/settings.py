"""A composed config's numbers checked before anything is built: one line naming the key the user sets
(``scale.lr``, not the ``model.optimizer.lr`` it flows into) and what was expected.

The frequency limit comes from ``benchmarks/encoding_precision.py`` (docs/numerics.md): for points of a
scene within |x| < 10 held in float32, features of frequency 2^k pi with k >= 19 are noise (mean error
0.05, largest 0.69). The limit applies to the frequencies the encoding sees, so an ``input_scale`` below
1 (gamma(s x)) allows larger L.
"""

import math
from collections.abc import Callable

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from nerfexp.errors import ConfigError
from nerfexp.extras import require

FLOAT32_TOP_OCTAVE = 18  # the largest k of sin(2^k pi x) still meaningful for float32 positions (see above)

POSITIVE = ("a finite number > 0",
            lambda v: isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and v > 0)
COUNT = ("a whole number >= 1", lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 1)
COUNT_OR_ALL = ("a whole number >= 1, or null for all", lambda v: v is None or COUNT[1](v))
NONNEGATIVE_COUNT = ("a whole number >= 0", lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0)

RULES: dict[str, tuple[str, Callable[[object], bool]]] = {  # key -> (what is expected, the test)
    "model.optimizer.lr": POSITIVE,
    "model.lr_final": POSITIVE,
    "model.lr_warmup_steps": NONNEGATIVE_COUNT,
    "model.chunk": COUNT,
    "datamodule.batch_rays": COUNT,
    "trainer.max_steps": COUNT,
    "trainer.val_check_interval": COUNT,
    "model.renderer.n_coarse": COUNT,
    "model.renderer.n_fine": COUNT,
    "model.renderer.n_single": COUNT,
    "data.n_train": COUNT_OR_ALL,
    "data.n_val": COUNT,
    "data.n_test": COUNT,
    "data.fps": POSITIVE,  # data=colmap data.video: frames kept per second of video
}


def named(cfg: DictConfig, key: str, value) -> str:
    """``KEY=VALUE`` as the user sets it: where ``key``'s value is a plain interpolation (``${scale.lr}``),
    the key it names, and which key it sets; else ``key`` itself."""
    parent, _, leaf = key.rpartition(".")
    node = (OmegaConf.select(cfg, parent) if parent else cfg)._get_node(leaf)
    raw = node._value() if node is not None else None
    if isinstance(raw, str) and raw.startswith("${") and raw.endswith("}") and raw.count("$") == 1 and ":" not in raw:
        return f"{raw[2:-1]}={value} (which sets {key})"
    return f"{key}={value}"


def check_extras(cfg: DictConfig) -> None:
    """A MissingExtraError (a ConfigError) where the config asks for a part of nerfexp whose optional
    package is not installed (``nerfexp.extras``)."""
    if str(OmegaConf.select(cfg, "data._target_", default="")).startswith("nerfexp.data.colmap."):
        require("pycolmap", "data=colmap")
    if OmegaConf.select(cfg, "data.video", default=None, throw_on_missing=False) is not None:
        require("imageio_ffmpeg", "data.video")


def check_settings(cfg: DictConfig) -> None:
    """A ConfigError for the first value that breaks a rule: ``RULES``, and positional encodings'
    ``n_freqs`` (a whole number >= 0 whose top frequency float32 positions still resolve); then
    ``check_extras``."""
    for key, (expected, valid) in RULES.items():
        value = OmegaConf.select(cfg, key, default="<absent>", throw_on_missing=False)
        if value != "<absent>" and not valid(value):
            raise ConfigError(f"{named(cfg, key, value)}: expected {expected}")
    for name in ("position", "direction"):
        encoding = OmegaConf.select(cfg, f"encoding.{name}")
        if encoding is None or "n_freqs" not in encoding:
            continue
        key, n_freqs = f"encoding.{name}.n_freqs", encoding.n_freqs
        if not NONNEGATIVE_COUNT[1](n_freqs):
            raise ConfigError(f"{key}={n_freqs}: expected {NONNEGATIVE_COUNT[0]} (0: the raw input alone)")
        scale = encoding.get("input_scale", 1.0)
        if not POSITIVE[1](scale):
            raise ConfigError(f"{named(cfg, f'encoding.{name}.input_scale', scale)}: expected {POSITIVE[0]}")
        top = n_freqs - 1 + math.log2(scale)  # the octave of the highest frequency the encoding sees
        if n_freqs > 0 and top > FLOAT32_TOP_OCTAVE:
            most = FLOAT32_TOP_OCTAVE + 1 - math.log2(scale)
            raise ConfigError(f"{key}={n_freqs}: frequencies above 2^{FLOAT32_TOP_OCTAVE} pi are noise for float32 "
                              f"positions (docs/numerics.md); use at most {math.floor(most)} with input_scale "
                              f"{scale:g}")
    check_extras(cfg)


class SettingsCheck(Callback):
    """Hydra callback (``hydra.callbacks.settings``): ``check_settings`` on a single run's config before
    Hydra creates its directory, so that a bad value leaves nothing behind; each job of a sweep is
    checked by ``nerfexp.train`` (the sweep's values differ per job). It stops with ``SystemExit``:
    Hydra turns a callback's exceptions into warnings and goes on."""

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        try:
            check_settings(config)
        except ConfigError as error:
            raise SystemExit(f"nerfexp: error: {error}") from None
