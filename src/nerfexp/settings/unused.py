"""Settings that do nothing with the rest of the config. A key does something when what nerfexp builds or reads
(``ROOTS``: the model, the data module, the trainer, ...) holds it, directly or through the references that
carry it there (``model.optimizer.lr: ${scale.lr}``, ``datamodule.scene: ${data}``), and no component on the way
declares it idle: a component's ``APPLIES`` (``nerfexp.domains``) says when one of its arguments does nothing
(``HierarchyChoice``'s ``n_fine`` without the hierarchy), and ``CROSSING`` holds the few rules that span several
components. A key nothing reads (``scale.lr`` where ``optimizer=ngp`` sets its own rate) is named with the
choice that left it unread and the options that read it.

A user's override of a key that does nothing stops a single run (``check_used``); in a sweep, whose jobs combine
values, the job runs and its record holds null for it (``without_unused``).
"""

import functools
from collections.abc import Callable, Mapping
from importlib.resources import files

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from nerfexp.config_keys import entries, reference
from nerfexp.errors import ConfigError
from nerfexp.settings.schema import component_class, matching

ROOTS = ("model", "datamodule", "trainer", "callbacks", "logger", "seed", "threads", "test_budgets", "resume", "tags",
         "notes")


def lpips_scored(cfg: DictConfig) -> str | None:
    return None if cfg.model.lpips is not False else "model.lpips=false (LPIPS is not scored)"


def boxed(cfg: DictConfig) -> str | None:
    if OmegaConf.select(cfg, "contraction.function") is not None:
        return "contraction=mipnerf360 (the grids work in the contraction's box, [-2, 2]^3)"
    uses = OmegaConf.select(cfg, "acceleration.grid") is not None or "log2_table_size" in cfg.encoding.position
    return None if uses else "acceleration=none and encoding other than hashgrid (nothing reads the box)"


def far_bounded(cfg: DictConfig) -> str | None:
    if OmegaConf.select(cfg, "contraction.function") is not None:
        return "contraction=mipnerf360 (rays end contraction.function.far radii away)"
    return None


# Rules that span components (key pattern -> why it is unused, or None): the box serves the grid or the hash grid,
# the far bound rays without a contraction (the scene reads it too, for its box), the weights the LPIPS scorer of
# the module.
CROSSING: dict[str, Callable[[DictConfig], str | None]] = {
    "data.aabb": boxed,
    "data.far": far_bounded,
    "model.lpips_weights": lpips_scored,
    "model.lpips_custom": lpips_scored,
}


def overridden_key(override: str) -> str:
    """The key of a Hydra override (``+scale.n_fine=64`` -> ``scale.n_fine``)."""
    return override.split("=", 1)[0].lstrip("+~")


def readers(plain: dict) -> dict[str, list[str]]:
    """For each key that another key's value names in a plain reference (``${scale.lr}``), those keys."""
    found: dict[str, list[str]] = {}
    for key, raw in entries(plain):
        if (named := reference(raw)) is not None:
            found.setdefault(named, []).append(key)
    return found


def idle_reason(cfg: DictConfig, key: str) -> str | None:
    """Why the components on the way to ``key`` (a key under ``ROOTS``) leave it idle (their ``APPLIES``), or
    None where none does."""
    parts = key.split(".")
    for depth in range(1, len(parts)):
        node = OmegaConf.select(cfg, ".".join(parts[:depth]))
        if not isinstance(node, DictConfig) or "_target_" not in node:
            continue
        applies = getattr(component_class(node.get("_target_")), "APPLIES", {})
        if parts[depth] in applies:
            reason = applies[parts[depth]](OmegaConf.to_container(node, resolve=True))
            if reason:
                return reason
    return None


@functools.cache
def options_reading(key: str) -> dict[str, list[str]]:
    """The options of nerfexp's config groups whose file reads ``key`` (``${key}``): {group: [option, ...]}."""
    found: dict[str, list[str]] = {}
    for folder in files("nerfexp.conf").iterdir():
        if folder.is_dir():
            for option in sorted(folder.iterdir(), key=lambda path: path.name):
                if option.name.endswith(".yaml") and f"${{{key}}}" in option.read_text():
                    found.setdefault(folder.name, []).append(option.name.removesuffix(".yaml"))
    return found


def chooser(group: str, option: str, chosen: Mapping) -> str:
    """`` (chosen by GROUP=OPTION)`` where another chosen option's defaults chose ``group``'s ``option``."""
    for other, other_option in chosen.items():
        path = files("nerfexp.conf") / other / f"{other_option}.yaml"
        if other != group and isinstance(other_option, str) and path.is_file() \
                and f"override /{group}: {option}" in path.read_text():
            return f", which {other}={other_option} chooses"
    return ""


def unread_reason(key: str, chosen: Mapping) -> str:
    """Why nothing reads ``key``: the chosen options of the groups whose other options read it."""
    reading = options_reading(key)
    said = [f"{group}={chosen.get(group)}{chooser(group, chosen.get(group), chosen)} ({group}="
            f"{', '.join(options)} read{'s' if len(options) == 1 else ''} {key})" for group, options in reading.items()
            if chosen.get(group) not in options]
    return "; ".join(said) or "this config (nothing in it reads the key)"


def unused_reason(cfg: DictConfig, key: str, chosen: Mapping, plain: dict | None = None,
                  seen: frozenset[str] = frozenset()) -> str | None:
    """Why ``key`` does nothing in ``cfg`` (its groups' options ``chosen``), or None where it does something
    (see the module's docstring)."""
    if (pattern := matching(CROSSING, key)) is not None and (reason := CROSSING[pattern](cfg)):
        return reason
    if key.split(".")[0] in ROOTS:
        return idle_reason(cfg, key)
    plain = OmegaConf.to_container(cfg, resolve=False) if plain is None else plain
    carried = [reader + key[len(named):] for named, keys in readers(plain).items() for reader in keys
               if (key == named or key.startswith(f"{named}.")) and reader not in seen]
    if not carried:
        return unread_reason(key, chosen)
    reasons = [unused_reason(cfg, reader, chosen, plain, seen | {key}) for reader in carried]
    return None if None in reasons else reasons[0]


def group_choices(cfg: DictConfig) -> Mapping:
    """The config groups' options of the run of ``cfg``: its ``hydra.runtime.choices``, else (a job's own
    config, which has no ``hydra``) the running job's; none outside Hydra."""
    if "hydra" in cfg:
        return cfg.hydra.runtime.choices
    return HydraConfig.get().runtime.choices if HydraConfig.initialized() else {}


def unused_settings(cfg: DictConfig, overrides: list[str]) -> list[tuple[str, str]]:
    """The ``overrides`` a user gave whose key does nothing with the rest of ``cfg`` (``unused_reason``), each
    with the reason: [(override, reason)]. Defaults the user did not set are never listed."""
    chosen, plain = group_choices(cfg), OmegaConf.to_container(cfg, resolve=False)
    unused = []
    for override in overrides:
        key = overridden_key(override)
        if key in chosen or key.split(".")[0] == "hydra" or not has_key(plain, key):
            continue  # a group's option, Hydra's own, or a key removed by a later override (~key)
        if reason := unused_reason(cfg, key, chosen, plain):
            unused.append((override, reason))
    return unused


def has_key(plain: dict, key: str) -> bool:
    """Whether the plain containers ``plain`` hold the dotted ``key`` (list items by index)."""
    node = plain
    for part in key.split("."):
        if isinstance(node, dict) and part in node:
            node = node[part]
        elif isinstance(node, list) and part.isdigit() and int(part) < len(node):
            node = node[int(part)]
        else:
            return False
    return True


def without_unused(cfg: DictConfig, resolved: dict, overrides: list[str]) -> dict:
    """``resolved`` (``cfg`` resolved, as a run records it) with null for each key of ``overrides`` (unused
    settings of a sweep's job, ``unused_settings``) and for each key that is a plain interpolation of one
    (``sampler.n_fine: ${scale.n_fine}``), or lies in a section that one names (``model.renderer.sampler.n_fine``
    through ``model.renderer.sampler: ${sampler}``): the record says what the run used, not what was asked."""
    keys = {overridden_key(o) for o in overrides}
    references = [(key, named) for key, raw in entries(OmegaConf.to_container(cfg, resolve=False))
                  if (named := reference(raw)) is not None]
    while new := {key + unused[len(named):] for key, named in references for unused in keys
                  if unused == named or unused.startswith(f"{named}.")} - keys:
        keys |= new  # a reference to a section carries its keys (model.renderer.sampler: ${sampler}), to the end
    recorded = OmegaConf.create(resolved)
    for key in keys:
        OmegaConf.update(recorded, key, None, force_add=False)
    return OmegaConf.to_container(recorded)


def check_used(cfg: DictConfig, overrides: list[str]) -> None:
    """A ConfigError for the first of ``overrides`` that does nothing (``unused_settings``)."""
    for override, reason in unused_settings(cfg, overrides)[:1]:
        raise ConfigError(f"{override}: not used with {reason}")
