"""Settings that do nothing with the rest of the config. A key does something when what nerfexp builds or reads
(``ROOTS``: the model, the data module, the trainer, ...) holds it, directly or through the references that
carry it there (``model.optimizer.lr: ${scale.lr}``, ``datamodule.scene: ${data}``), and no component on the way
declares it idle: a component's ``APPLIES`` (``nerfexp.domains``) says when one of its arguments does nothing
(``HierarchyChoice``'s ``n_fine`` without the hierarchy). A scene's setting that only other components read (its
``SERVES``: the box) does nothing unless a component built reads it (their ``SCENE_FIELDS``), and a component built
may take a scene setting's place (its ``REPLACES_SCENE``: a contraction's box and far); ``CROSSING`` holds the rules
of the keys no component owns. A key nothing reads (``scale.lr`` where ``optimizer=ngp`` sets its own rate) is
named with the choice that left it unread and the options that read it, found by reading the options' files.

A user's override of a key that does nothing stops a single run (``check_used``); in a sweep, whose jobs combine
values, the job runs and its record holds null for it (``without_unused``).
"""

from collections.abc import Callable, Iterator, Mapping

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from nerfexp.config_keys import entries, readers, reference, source_key
from nerfexp.errors import ConfigError
from nerfexp.settings.components import ROOTS, arguments, components, walked_once
from nerfexp.settings.options import option_files, options_reading, options_where
from nerfexp.settings.schema import component_class, matching


def lpips_scored(cfg: DictConfig) -> str | None:
    return None if cfg.model.lpips is not False else "model.lpips=false (LPIPS is not scored)"


# Rules of keys no component owns (key pattern -> why it is unused, or None): the weights serve the LPIPS scorer of
# the module.
CROSSING: dict[str, Callable[[DictConfig], str | None]] = {
    "model.lpips_weights": lpips_scored,
    "model.lpips_custom": lpips_scored,
}


def scene_reason(cfg: DictConfig, key: str, chosen: Mapping) -> str | None:
    """Why ``key``, a setting of a scene the config builds, does nothing: a component built takes its place
    (``REPLACES_SCENE``), or it is one the scene holds for other components (``SERVES``) and none built reads it
    (``SCENE_FIELDS``); None where neither."""
    section, _, argument = key.rpartition(".")
    node = OmegaConf.select(cfg, section, throw_on_resolution_failure=False) if section else None
    if not isinstance(node, DictConfig) or not hasattr(component_class(node.get("_target_")), "SERVES"):
        return None  # not a scene's setting (most keys): no component needs asking
    built = list(components(cfg))
    if not any(c.key == section and hasattr(c.cls, "SERVES") for c in built):
        return None
    for component in built:
        if (reason := getattr(component.cls, "REPLACES_SCENE", {}).get(argument)) is not None:
            return reason
    serves = next(c.cls.SERVES for c in built if c.key == section)
    if argument not in serves or any(argument in getattr(c.cls, "SCENE_FIELDS", ()) for c in built):
        return None
    return described(options_with(lambda cls: argument in getattr(cls, "SCENE_FIELDS", ())), key, chosen)


def overridden_key(override: str) -> str:
    """The key of a Hydra override (``+scale.n_fine=64`` -> ``scale.n_fine``)."""
    return override.split("=", 1)[0].lstrip("+~")


def idle_reason(cfg: DictConfig, key: str) -> str | None:
    """Why the components on the way to ``key`` (a key under ``ROOTS``) leave it idle (their ``APPLIES``), or
    None where none does."""
    parts = key.split(".")
    for depth in range(1, len(parts)):
        node = OmegaConf.select(cfg, ".".join(parts[:depth]))
        if not isinstance(node, DictConfig) or "_target_" not in node:
            continue
        cls = component_class(node.get("_target_"))
        applies = getattr(cls, "APPLIES", {})
        if parts[depth] in applies:
            reason = applies[parts[depth]](arguments(cfg, source_key(cfg, ".".join(parts[:depth])), cls, node))
            if reason:
                return reason
    return None


def targets(content: dict) -> Iterator[type]:
    """The classes of the components an option's ``content`` sets (``component_class`` of each ``_target_``)."""
    for key, value in entries(content):
        if key.rpartition(".")[2] == "_target_" and (cls := component_class(value)) is not None:
            yield cls


def options_with(test: Callable[[type], bool]) -> dict[str, list[str]]:
    """The options that set a component whose class passes ``test``: {group: [option, ...]}."""
    return options_where(lambda content: any(map(test, targets(content))))


def chooser(group: str, option: str, chosen: Mapping) -> str:
    """``, which OTHER=OPTION chooses`` where another chosen option's defaults chose ``group``'s ``option``."""
    choosing = {(other, other_option) for other, other_option, content in option_files()
                if any(isinstance(entry, dict) and entry.get(f"override /{group}") == option
                       for entry in content.get("defaults", []))}
    for other, other_option in chosen.items():
        if other != group and (other, other_option) in choosing:
            return f", which {other}={other_option} chooses"
    return ""


def described(reading: dict[str, list[str]], key: str, chosen: Mapping) -> str:
    """Why ``key`` is unread: the chosen options of the groups whose other options (``reading``) read it."""
    said = [f"{group}={chosen.get(group)}{chooser(group, chosen.get(group), chosen)} ({group}="
            f"{', '.join(options)} read{'s' if len(options) == 1 else ''} {key})" for group, options in reading.items()
            if chosen.get(group) not in options]
    return "; ".join(said) or "this config (nothing in it reads the key)"


def unread_reason(key: str, chosen: Mapping) -> str:
    """Why nothing reads ``key``: the chosen options of the groups whose other options read it."""
    return described(options_reading(key), key, chosen)


def unused_reason(cfg: DictConfig, key: str, chosen: Mapping, plain: dict | None = None,
                  seen: frozenset[str] = frozenset()) -> str | None:
    """Why ``key`` does nothing in ``cfg`` (its groups' options ``chosen``), or None where it does something
    (see the module's docstring)."""
    if (pattern := matching(CROSSING, key)) is not None and (reason := CROSSING[pattern](cfg)):
        return reason
    if reason := scene_reason(cfg, key, chosen):
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
    with walked_once(cfg):  # each key asks the components again, of a config that stays as it is
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
