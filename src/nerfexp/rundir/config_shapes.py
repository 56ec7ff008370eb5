"""What each key of a config is, whatever its value (its shape), and the shapes nerfexp's own config files give
their keys: a run read back is built only in those shapes.

A key's shape (``Shape``) is whether it is a section (a mapping) or a value (a number, a text, null, a list), and
for a section, the class it builds (``_target_``, or none) and whether it is built partially (``_partial_``, false
where it is not written, as Hydra reads it). The value itself is each key's domain's to check (the settings check);
a change of shape is what no domain sees: ``sampler: evil`` hands the renderer a text where it calls a sampler, and
``_partial_: false`` builds a field where the renderer expects something that builds one, each a traceback deep in
the code that was handed it. So, before anything is built from a run read back (``nerfexp.rundir.trained.run_config``):

- ``check_own_shapes``: the saved config itself, as resolved (a reference to a section is that section), has at
  each key that nerfexp's own config files give (``own_keys``: the groups, the sweeps and rows, ``config.yaml``,
  each at its package, references carried to the keys that hold them) a shape they give it there: a section or a
  value as one of them has it, a class where they build one, and its ``_partial_`` as theirs. A key none of them
  gives (one of an earlier version, a key of the user's own) is the settings check's.
- ``with_overrides``: the ``KEY=VALUE`` overrides of a command that reads a run back change values, never
  a shape of the run's config: no section becomes a value or a value a section (``sampler=evil``,
  ``scale.width={a: 1}``), and no ``_partial_`` changes; a ``_target_`` may name another class its key allows
  (``nerfexp.rundir.saved_configs.check_targets``).
"""

import functools
from collections.abc import Iterator
from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path
from typing import NamedTuple

import yaml
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from nerfexp.config_keys import entries, reference
from nerfexp.domains import yaml_word
from nerfexp.errors import ConfigError

SECTION = "a section"  # a mapping of keys
VALUE = "a value"  # a number, a text, null or a list: what a key's domain checks
PACKAGE = "# @package "  # a config file's header naming where its keys go (Hydra's package)


class Shape(NamedTuple):
    """What a key of a config is (see the module's docstring)."""

    kind: str  # SECTION or VALUE
    target: object = None  # a section's _target_, None where it names none
    partial: object = False  # a section's _partial_, False where not written (Hydra's default)


@dataclass(frozen=True)
class Allowed:
    """The shapes a key may have: those nerfexp's own config files give it (``own_keys``), or the one a run's config
    gives it (``kept``)."""

    kinds: frozenset[str]  # SECTION, VALUE
    targets: frozenset[str] = frozenset()  # the classes named as its _target_: a section there must name one
    partials: frozenset[object] = frozenset()  # its _partial_ where a section there builds a class (see own_keys)
    # a class's own _partial_ where a file writes the two together ((class, values) pairs): a section naming that
    # class must have one of those values (``sampler=paper``'s whole HierarchyChoice, ``sampler=march``'s partial
    # GridMarchSampler); a class named without its _partial_ takes the key's (``partials``)
    paired: tuple[tuple[str, frozenset], ...] = ()

    def partials_of(self, target: object) -> frozenset:
        """The ``_partial_`` values a section naming ``target`` may have: its own (``paired``), else the key's."""
        return next((values for named, values in self.paired if named == target), self.partials)


def kept(shape: Shape) -> Allowed:
    """The shapes a key whose shape is ``shape`` may have after an override: the same kind, a class where it builds
    one, and the same ``_partial_`` where it is a section."""
    return Allowed(frozenset([shape.kind]), frozenset() if shape.target is None else frozenset([shape.target]),
                   frozenset([shape.partial]) if shape.kind == SECTION else frozenset())


def package(text: str, group: str) -> str:
    """Where the keys of a config file of ``group`` (its folder under ``conf/``, ``""`` for ``config.yaml``) go, as
    Hydra places them: the dotted key its header names (``# @package model.renderer.field``; ``_global_``: the
    top), else the group's own (``appearance``, ``hydra/launcher``: ``hydra.launcher``)."""
    for line in text.splitlines():
        if not line.startswith("#"):
            break
        if line.startswith(PACKAGE):
            named = line.removeprefix(PACKAGE).strip()
            return "" if named == "_global_" else named
    return group.replace("/", ".")


def referenced_key(key: str, raw: object) -> str | None:
    """The key that ``raw``, the value at the dotted ``key``, names where it is a plain reference, absolute
    (``${acceleration.grid}``) or relative to the section holding ``key`` (``${.near}``, ``${..near}``: a dot
    more for each section up); else None."""
    named = reference(raw)
    if named is None or not named.startswith("."):
        return named
    dots = len(named) - len(named.lstrip("."))
    base = key.split(".")[:-dots]
    return ".".join([*base, named[dots:]])


def under(key: str, section: str) -> str | None:
    """What follows ``section`` in the dotted ``key`` (``""`` for the section itself, ``.x`` below it), or None
    where ``key`` is not in it."""
    return key[len(section):] if key == section or key.startswith(f"{section}.") else None


def own_files() -> Iterator[tuple[str, dict]]:
    """Each YAML file of the packaged ``nerfexp.conf`` (the groups, the sweeps, the rows, ``config.yaml``): its
    package (``package``) and its content without its defaults list."""
    pending = [(files("nerfexp.conf"), "")]
    while pending:
        folder, group = pending.pop()
        for item in folder.iterdir():
            name = f"{group}/{item.name}" if group else item.name
            if item.is_dir():
                pending.append((item, name))
            elif item.name.endswith(".yaml"):
                text = item.read_text()
                content = yaml.safe_load(text) or {}
                content.pop("defaults", None)
                yield package(text, group), content


@functools.cache
def own_keys() -> dict[str, Allowed]:
    """{a dotted key: the shapes nerfexp's own config files give it} (``own_files``), each file at its package, with
    each plain reference carrying what the key it names has to the key holding it, and to the keys below
    (``model.renderer.field.view_head.direction_encoding``), to the end. A reference itself is no shape: the key
    holding it has the shapes of the key it names. A section's ``_partial_`` is read where a file writes it (a file
    may set a section's ``_target_`` alone, over a section another file makes: ``sweeps/sparse_tables.yaml``'s
    optimizer); where none writes it at a key that builds a class, it is false there (Hydra's default)."""
    found: dict[str, tuple[set, set, set]] = {}  # key -> (kinds, targets, the _partial_ values written)
    paired: dict[str, dict[str, set]] = {}  # key -> {a class: the _partial_ values written with it}
    aliases: list[tuple[str, str]] = []  # (the key holding a reference, the key it names)
    for prefix, content in own_files():
        for key, value in [*([(prefix, content)] if prefix else []), *entries(content, prefix)]:
            if (named := referenced_key(key, value)) is not None:
                aliases.append((key, named))
                continue
            kinds, targets, partials = found.setdefault(key, (set(), set(), set()))
            kinds.add(SECTION if isinstance(value, dict) else VALUE)
            if isinstance(value, dict) and isinstance(value.get("_target_"), str):
                targets.add(value["_target_"])
            if isinstance(value, dict) and "_partial_" in value:
                partials.add(value["_partial_"])
                if isinstance(value.get("_target_"), str):
                    paired.setdefault(key, {}).setdefault(value["_target_"], set()).add(value["_partial_"])
    changed = True
    while changed:  # a reference to a section holding a reference: carried until nothing more is
        changed = False
        for key, named in aliases:
            for other, facts in list(found.items()):
                rest = under(other, named)
                if rest is None:
                    continue
                held = found.setdefault(key + rest, (set(), set(), set()))
                for mine, theirs in zip(held, facts):
                    if not theirs <= mine:
                        mine |= theirs
                        changed = True
    for key, named in aliases:  # a reference's key has the pairs of the key it names, and of the keys below
        for other, pairs in list(paired.items()):
            if (rest := under(other, named)) is not None:
                for target, values in pairs.items():
                    paired.setdefault(key + rest, {}).setdefault(target, set()).update(values)
    return {key: Allowed(frozenset(kinds), frozenset(targets), frozenset(partials or ({False} if targets else ())),
                         tuple((target, frozenset(values)) for target, values in paired.get(key, {}).items()))
            for key, (kinds, targets, partials) in found.items()}


def shapes(cfg: DictConfig) -> dict[str, Shape]:
    """{each dotted key of ``cfg``: its ``Shape``}: a reference is followed (a key naming a section is that section,
    its keys walked under it) and a list is a value, not walked. The keys where the config writes them come first,
    in its order, a section before its keys; then those reached through a reference
    (``model.renderer.sampler.n_coarse``), so that a key is named where it is set. A key that cannot be resolved (a
    reference that leads nowhere, or back into a section on its way) is left out: resolving the config names it."""
    written: dict[str, Shape] = {}
    referenced: dict[str, Shape] = {}

    def walk(node: DictConfig, prefix: str, inside: tuple[int, ...], found: dict[str, Shape]) -> None:
        for name in node.keys():
            key = f"{prefix}{name}"
            if OmegaConf.is_missing(node, name):
                found[key] = Shape(VALUE)
                continue
            try:
                child = node[name]
                section = isinstance(child, DictConfig)
                shape = Shape(SECTION, child.get("_target_"), child.get("_partial_", False)) if section \
                    else Shape(VALUE)
            except OmegaConfBaseException:
                continue
            if section and id(child) in inside:  # a reference back to a section on its way: no end
                continue
            held = referenced if OmegaConf.is_interpolation(node, name) else found
            held[key] = shape
            if section:
                walk(child, f"{key}.", (*inside, id(child)), held)

    walk(cfg, "", (id(cfg),), written)
    return {**written, **referenced}


def shape_problem(key: str, shape: Shape, allowed: Allowed, whose: str) -> str | None:
    """What is wrong with ``shape``, the shape of ``key``, where ``whose`` (``nerfexp's configs have``, ``the run's
    config has``) give it one of the shapes ``allowed``; None where nothing is."""
    if shape.kind not in allowed.kinds:
        return f"{key} is {shape.kind} where {whose} {' or '.join(sorted(allowed.kinds))}"
    if shape.kind == SECTION and allowed.targets and shape.target is None:
        return f"{key} has no _target_ where {whose} one ({', '.join(sorted(allowed.targets))})"
    partials = allowed.partials_of(shape.target)
    if shape.kind == SECTION and partials and shape.partial not in partials:
        return (f"{key}._partial_={yaml_word(shape.partial)} where {whose} "
                f"_partial_: {' or '.join(sorted(map(yaml_word, partials)))}")
    return None


def check_own_shapes(cfg: DictConfig, source: Path) -> None:
    """A ConfigError naming ``source`` (the file the saved config ``cfg`` came from) and the key, for the first key
    whose shape (``shapes``) is not one nerfexp's own config files give it (``own_keys``; see the module's
    docstring)."""
    own = own_keys()
    for key, shape in shapes(cfg).items():
        if key not in own:
            continue
        problem = shape_problem(key, shape, own[key], "nerfexp's configs have")
        if problem is not None:
            raise ConfigError(f"{source}: {problem}: a run directory from elsewhere is read as data, in the shapes "
                              "nerfexp's own configs give its keys")


def with_overrides(cfg: DictConfig, overrides: list[str], source: Path) -> DictConfig:
    """``cfg`` (the run's saved config, from ``source``; struct: an override of a key it does not have is a typo)
    with ``overrides`` (``KEY=VALUE``) applied in turn; a ConfigError naming the first that changes a shape of the
    config (``override_problem``) or cannot be applied (OmegaConf's reason: a key the run does not have)."""
    before = shapes(cfg)
    for override in overrides:
        try:
            given = OmegaConf.from_dotlist([override])
            problem = override_problem(before, override.partition("=")[0], given, None)
            if problem is None:
                cfg = OmegaConf.merge(cfg, given)
                problem = override_problem(before, override.partition("=")[0], given, shapes(cfg))
        except OmegaConfBaseException as error:
            raise ConfigError(f"cannot apply {override} to {source}: {str(error).splitlines()[0]}") from None
        if problem is not None:
            raise ConfigError(f"cannot apply {override} to {source}: {problem}: an argument of a command that reads a "
                              "run back changes values, never the shape of the run's config")
    return cfg


def override_problem(before: dict[str, Shape], named: str, given: DictConfig,
                     after: dict[str, Shape] | None) -> str | None:
    """How the override of the key ``named`` with the config ``given`` (``OmegaConf.from_dotlist``) changes a shape
    of a config whose shapes were ``before`` (``shapes``), or None where it changes none: before it is merged
    (``after`` None), where the value given is another kind than the key's (a section for a value, or back: OmegaConf
    cannot merge a section with a list); merged (``after``: the shapes then), the first key whose shape changed, the
    key it sets first (``scale.width={a: 1}`` changes ``model.renderer.field.width`` too)."""
    if after is None:
        kind = SECTION if isinstance(OmegaConf.select(given, named), DictConfig) else VALUE
        return None if named not in before else shape_problem(named, Shape(kind), Allowed(
            frozenset([before[named].kind])), "the run's config has")
    for key, was in sorted(before.items(), key=lambda item: under(item[0], named) is None):  # its own key first
        if key not in after:  # below a key whose shape changed (named first), or no longer resolved
            continue
        if (problem := shape_problem(key, after[key], kept(was), "the run's config has")) is not None:
            return problem
    return None
