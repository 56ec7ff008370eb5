"""A config read key by key, each key a dotted path (``model.optimizer.lr``, ``scale.skips.0``): its leaves,
resolved (``leaves``, of a DictConfig) or as they are written (``entries``, of its plain containers), and
the key that an interpolated value comes from (``source_key``) and the keys that read a key (``readers``).

The settings check (``nerfexp.settings``), the settings a checkpoint records (``nerfexp.training.resume``)
and the check of a run's saved config (``nerfexp.rundir.saved_configs``) read configs through these, so
that a key is spelled, and an interpolation followed, one way everywhere.
"""

from collections.abc import Callable, Iterator

from omegaconf import MISSING, DictConfig, ListConfig, OmegaConf
from omegaconf.errors import InterpolationToMissingValueError


def reference(raw: object) -> str | None:
    """The key that the unresolved value ``raw`` names where it is a plain interpolation (``${scale.lr}``:
    ``scale.lr``); None for any other value (a resolver's ``${hydra:...}``, text around one ``a/${b}``)."""
    if isinstance(raw, str) and raw.startswith("${") and raw.endswith("}") and raw.count("$") == 1 and ":" not in raw:
        return raw[2:-1]
    return None


def source_key(cfg: DictConfig, key: str) -> str:
    """The key a user sets for ``key`` of ``cfg``: where ``key`` or a key above it is a plain interpolation
    (``model.optimizer.lr: ${scale.lr}``, ``...position_encoding: ${encoding.position}``), the key it names
    (``scale.lr``, ``encoding.position...``), followed to its end; else ``key``."""
    parts = key.split(".")
    node = cfg
    for i, part in enumerate(parts):
        if not isinstance(node, DictConfig) or part not in node:
            return key
        if OmegaConf.is_interpolation(node, part):  # its text, from the section that holds it (never resolved)
            named = reference(OmegaConf.to_container(node, resolve=False)[part])
            return key if named is None else source_key(cfg, ".".join([named, *parts[i + 1:]]))
        node = node[part]
    return key


def leaves(cfg: DictConfig, skip: Callable[[str, object], bool] = lambda key, written: False,
           prefix: str = "") -> Iterator[tuple[str, object]]:
    """Each leaf of ``cfg`` as (dotted key, resolved value), ``hydra`` and the keys that ``skip(key, written)``
    names aside (``written``: the value as the config writes it, an interpolation its text, a section a plain
    container): a list is one leaf (a plain list), and a section that an interpolation names is walked
    under the key that names it (``datamodule.scene.root``). A value made from Hydra's runtime
    (``${hydra:runtime.output_dir}/...``) is given unresolved, its text: it exists only once the job runs. A
    mandatory value not set is ``MISSING`` (``???``), and an interpolation of one is left out: the key
    set to ``???`` is the one to name."""
    written = OmegaConf.to_container(cfg, resolve=False)
    for name in cfg.keys():
        key, raw = f"{prefix}{name}", written[name]
        if key == "hydra" or skip(key, raw):
            continue
        if isinstance(raw, str) and "${hydra:" in raw:
            yield key, raw
        elif OmegaConf.is_missing(cfg, name):
            yield key, MISSING
        else:
            try:
                value = cfg[name]
            except InterpolationToMissingValueError:
                continue
            if isinstance(value, DictConfig):
                yield from leaves(value, skip, f"{key}.")
            else:
                yield key, OmegaConf.to_container(value, resolve=True) if isinstance(value, ListConfig) else value


def entries(node, path: str = "") -> Iterator[tuple[str, object]]:
    """Every (dotted key, e.g. ``model.optimizer._target_`` or ``scale.skips.0``; value) of a config's plain
    containers (``OmegaConf.to_container``) at every depth, containers as well as what they hold."""
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for key, value in items:
        dotted = f"{path}.{key}" if path else str(key)
        yield dotted, value
        yield from entries(value, dotted)


def readers(plain: dict) -> dict[str, list[str]]:
    """For each key that another key's value names in a plain reference (``${scale.lr}``), those keys (of a
    config's plain containers, ``entries``)."""
    found: dict[str, list[str]] = {}
    for key, raw in entries(plain):
        if (named := reference(raw)) is not None:
            found.setdefault(named, []).append(key)
    return found
