"""A config read from someone else's run directory is data: it may build only the classes that nerfexp's own
configs build, and an interpolation in it may only refer to another of its keys.

Hydra builds whatever ``_target_`` a config names, so a crafted ``.hydra/config.yaml`` could call any
importable function (``torch.load`` of a pickle with ``weights_only: false``, say) the moment
``nerfexp-eval`` or ``nerfexp-render`` builds it. Before anything is built or resolved from a saved config
(``as_data``):

- The keys that only training builds are removed, unread (``TRAINING_ONLY``: the callbacks, the logger and
  the trainer's ``default_root_dir``, where a run wrote its files: the only keys of nerfexp's configs that
  call a resolver, ``${hydra:runtime.output_dir}``). The commands that read a run back build none of them.
- The keys that choose what the reader's own evaluation reads (``READERS_OWN``: the LPIPS weights file, whether
  it is the user's own) get nerfexp's defaults (``conf/config.yaml``'s), never the saved values: a run directory
  from elsewhere never chooses the weights that score LPIPS on the reader's machine; the reader's ``KEY=VALUE``
  overrides set them.
- Every interpolation left, nested ones included, must be a plain reference to another key (``${scale.width}``,
  ``${..near}``, ``${a.${b}}``). Any resolver (``oc.create``, which makes a node that Hydra then builds,
  ``oc.decode``, ``oc.env``, which would read the reader's environment, ``oc.select``, ``oc.dict.keys``,
  ``oc.dict.values``, ``oc.deprecated``, ``now``, ``hydra`` or any other) is refused, and so is an escaped
  interpolation (``\\${x}``, at any depth of escaping) and a key holding ``${``: resolving the config once
  turns escaped text into a live interpolation, which Hydra resolves again when it builds the objects
  (its ``instantiate`` resolves the config in place, then reads it). So the config is checked as it will
  be built: what a plain reference yields is another key of the same file, which is checked too.
- After the caller's overrides, the whole config is resolved once and no value or key of the result may
  hold ``${`` (``check_resolved``): whatever path text takes to become an interpolation, what reaches the
  objects is the plain string or number it is, and nothing outside the file reaches what is built or
  written.
- Every ``_target_`` must be one of:

  - a class defined in nerfexp (``nerfexp.*``, the class itself rather than something a module imported);
  - ``lightning.Trainer``;
  - a torch optimizer (a subclass of ``torch.optim.Optimizer`` from ``torch.optim``);
  - a Lightning logger or callback (a subclass of ``Logger`` / ``Callback`` from
    ``lightning.pytorch.loggers`` / ``lightning.pytorch.callbacks``);

  and one that its key allows (``allowed_at``): a class nerfexp's own config files (``conf/``, the sweeps
  and rows included) name at that key, directly or through the references that put a section of theirs
  there (``model.renderer.grid: ${acceleration.grid}``), or, where they name a torch optimizer, a Lightning
  logger or callback there, another of that kind (``model.optimizer._target_=torch.optim.SGD``). So a
  logger planted under the renderer, or a field where the appearance fit goes, is refused by its key. Both
  the file as written and the config resolved (where a reference lands a section elsewhere) are checked.

A config you compose yourself (``nerfexp ...`` with your overrides, ``KEY=VALUE`` arguments of the commands
that read a run back) is your own code, as in any Hydra application, and is not checked, but for this: the
arguments change a saved config, whose ``_target_``s are checked once more at their keys after them, and whose
shapes they may not change (``nerfexp.rundir.config_shapes``, which checks the saved config's own shapes too).
"""

import functools
from collections.abc import Iterator
from importlib.resources import files
from pathlib import Path

import yaml
from hydra.utils import get_class
from omegaconf import DictConfig, OmegaConf
from omegaconf.grammar.gen.OmegaConfGrammarLexer import OmegaConfGrammarLexer
from omegaconf.grammar_parser import parse
from omegaconf.grammar_visitor import OmegaConfGrammarParser

from nerfexp.config_keys import entries
from nerfexp.errors import ConfigError
from nerfexp.rundir.config_shapes import own_keys

TRAINERS = ("lightning.Trainer", "lightning.pytorch.Trainer")
# (where the target and its class live, their base): the bases imported only to check a target of theirs
FAMILIES = (("nerfexp.", "builtins.object"), ("torch.optim.", "torch.optim.Optimizer"),
            ("lightning.pytorch.loggers.", "lightning.pytorch.loggers.Logger"),
            ("lightning.pytorch.callbacks.", "lightning.pytorch.callbacks.Callback"))
OPEN_FAMILIES = FAMILIES[1:]  # the kinds a key naming one of them takes any of: torch's optimizers, Lightning's
TRAINING_ONLY = ("callbacks", "logger", "trainer.default_root_dir")  # what only training builds (dotted keys)
READERS_OWN = ("model.lpips", "model.lpips_weights", "model.lpips_custom")  # what the reader's evaluation reads


def targets(node, path: str = "") -> Iterator[tuple[str, object]]:
    """Every ``_target_`` in a config's plain containers (``nerfexp.config_keys.entries``): (its dotted key,
    its value)."""
    return ((key, value) for key, value in entries(node, path) if key.split(".")[-1] == "_target_")


def grammar_nodes(value: str) -> Iterator[object]:
    """The nodes of OmegaConf's parse tree of the string ``value`` (contexts and tokens), in the order
    written; none where it holds no ``${`` (OmegaConf's own test of whether a string is interpolated).
    Raises OmegaConf's GrammarParseError where ``value`` is not a string OmegaConf can resolve."""
    if "${" not in value:
        return
    pending = [parse(value)]
    while pending:
        node = pending.pop()
        yield node
        pending.extend(node.getChild(i) for i in reversed(range(node.getChildCount())))  # tokens have none


def resolvers(value: str) -> list[str]:
    """The resolvers that the string ``value`` calls when OmegaConf resolves it, in the order written, those
    in another interpolation's key or arguments included (``${a.${oc.env:X}}``: ``oc.env``); none where its
    interpolations are all plain references or it has none."""
    return [node.resolverName().getText() for node in grammar_nodes(value)
            if isinstance(node, OmegaConfGrammarParser.InterpolationResolverContext)]


def escapes_interpolation(value: str) -> bool:
    """Whether the string ``value`` holds an escaped interpolation (``\\${x}``, or ``\\\\\\${x}``: an escaped
    backslash before one), text that OmegaConf resolves to a live ``${x}``."""
    return any(node.getSymbol().type == OmegaConfGrammarLexer.ESC_INTER
               for node in grammar_nodes(value) if hasattr(node, "getSymbol"))  # the tokens


def buildable(target: object) -> bool:
    """Whether a saved config may build ``target`` (see the module's docstring). Only nerfexp's, torch's
    optimizers' and Lightning's own modules are imported to find out."""
    if not isinstance(target, str) or target in TRAINERS:
        return target in TRAINERS
    for prefix, base in FAMILIES:
        if target.startswith(prefix):
            try:
                cls = get_class(target)
            except (ImportError, ValueError):  # no such class (a function, a module, a missing name)
                return False
            return issubclass(cls, get_class(base)) and cls.__module__.startswith(prefix)
    return False


@functools.cache
def named_targets() -> dict[str, frozenset[str]]:
    """{the dotted key of a section: the classes nerfexp's own config files name as its ``_target_``}: every
    YAML file of the packaged ``nerfexp.conf`` (the groups, the sweeps, the rows, ``config.yaml``), each at its
    package, with each plain reference to a section carrying that section's classes to the key holding it, and to
    the keys below (``model.renderer.field.view_head.direction_encoding``), to the end
    (``nerfexp.rundir.config_shapes.own_keys``)."""
    return {key: facts.targets for key, facts in own_keys().items() if facts.targets}


def allowed_at(section: str, target: object) -> bool:
    """Whether a saved config may build ``target`` as the section at the dotted key ``section`` (see the
    module's docstring): a class nerfexp's own configs name there (``named_targets``), or, where they name one
    of ``OPEN_FAMILIES`` there, another class of that family (``buildable``)."""
    named = named_targets().get(section, frozenset())
    if target in named:
        return True
    return isinstance(target, str) and buildable(target) and any(
        target.startswith(prefix) and any(other.startswith(prefix) for other in named)
        for prefix, _ in OPEN_FAMILIES)


def check_targets(plain: dict, source: Path) -> None:
    """A ConfigError naming ``source``, the key and the class for the first ``_target_`` of ``plain`` (a saved
    config's containers, resolved or not) that a saved config may not build (``buildable``), or not at its key
    (``allowed_at``). Nothing is imported but nerfexp's, torch's optimizers' and Lightning's own modules."""
    for key, target in targets(plain):
        section = key.rpartition(".")[0]
        if not buildable(target):
            raise ConfigError(
                f"{source}: {key}={target!r} is not a class nerfexp builds from a run's saved config (nerfexp's "
                "own classes, lightning.Trainer, torch optimizers, Lightning loggers and callbacks): a run "
                "directory from elsewhere is read as data, never run")
        if not allowed_at(section, target):
            named = sorted(named_targets().get(section, ()))
            expected = f"its configs name {', '.join(named)} there" if named else "its configs build nothing there"
            raise ConfigError(
                f"{source}: {key}={target!r} is not a class nerfexp builds at {section} ({expected}): a run "
                "directory from elsewhere is read as data, never run")


def check_saved_config(plain: dict, source: Path) -> None:
    """A ConfigError naming ``source`` (the file the config came from) and the key for the first key of
    ``plain`` (a saved config's containers, unresolved) that holds ``${``, or value that calls a resolver
    (``resolvers``) or holds an escaped interpolation (``escapes_interpolation``), then for the first
    ``_target_`` that a saved config may not build, or not at its key (``check_targets``). Nothing is built or
    resolved."""
    for key, value in entries(plain):
        if "${" in key:
            raise ConfigError(f"{source}: the key {key!r} holds '${{': a run directory from elsewhere is read as "
                              "data: its keys are names, never interpolations")
        called = resolvers(value) if isinstance(value, str) else []
        if called:
            raise ConfigError(
                f"{source}: {key}={value!r} uses the resolver {called[0]}: a run directory from elsewhere is read "
                "as data: only plain references ${key} to its own keys are followed")
        if isinstance(value, str) and escapes_interpolation(value):
            raise ConfigError(
                f"{source}: {key}={value!r} holds an escaped interpolation, text that becomes a live one when the "
                "run's objects are built: a run directory from elsewhere is read as data: only plain references "
                "${key} to its own keys are followed")
    check_targets(plain, source)


def check_resolved(resolved: dict, source: Path) -> None:
    """A ConfigError naming ``source`` and the key where a value or key of ``resolved`` (a saved config's
    containers after the caller's overrides, resolved once) holds ``${``: text that Hydra would resolve
    again when it builds the objects; then where a ``_target_`` is not one its key allows (``check_targets``:
    a reference may have landed a section where another belongs)."""
    for key, value in entries(resolved):
        if "${" in key or (isinstance(value, str) and "${" in value):
            shown = f"the key {key!r}" if "${" in key else f"{key}, resolved, is {value!r}:"
            raise ConfigError(f"{source}: {shown} text with '${{' in it, which building the run's objects would "
                              "resolve again: a run directory from elsewhere is read as data, never resolved twice")
    check_targets(resolved, source)


def holder(plain: dict, dotted: str) -> tuple[dict | None, str]:
    """The container in the plain containers ``plain`` that holds the key ``dotted`` (e.g.
    ``trainer.default_root_dir``), and the key's last part; None where a parent is not there."""
    *parents, leaf = dotted.split(".")
    for key in parents:
        plain = plain.get(key) if isinstance(plain, dict) else None
    return (plain if isinstance(plain, dict) else None), leaf


def without(plain: dict, dotted: str) -> None:
    """Remove the key ``dotted`` (e.g. ``trainer.default_root_dir``) from the plain containers ``plain``, in
    place, where it is there; nothing is resolved."""
    container, leaf = holder(plain, dotted)
    if container is not None:
        container.pop(leaf, None)


def readers_own() -> dict[str, object]:
    """nerfexp's defaults of the ``READERS_OWN`` keys, from its own ``conf/config.yaml``: ``{dotted key: value}``."""
    defaults = OmegaConf.create(yaml.safe_load((files("nerfexp.conf") / "config.yaml").read_text()))
    return {dotted: OmegaConf.select(defaults, dotted) for dotted in READERS_OWN}


def put(plain: dict, dotted: str, value: object) -> None:
    """Set the key ``dotted`` (e.g. ``model.lpips``) of the plain containers ``plain`` to ``value``, in place,
    where its parent is there (a config without ``model`` is refused where it is built)."""
    container, leaf = holder(plain, dotted)
    if container is not None:
        container[leaf] = value


def as_data(cfg: DictConfig, source: Path) -> DictConfig:
    """The saved config ``cfg`` (read from ``source``, nothing resolved yet) as the commands that read a run
    back may use it: without ``TRAINING_ONLY``'s keys, the ``READERS_OWN`` keys at nerfexp's defaults
    (``readers_own``), checked (``check_saved_config``)."""
    plain = OmegaConf.to_container(cfg, resolve=False)
    for dotted in TRAINING_ONLY:
        without(plain, dotted)
    for dotted, value in readers_own().items():
        put(plain, dotted, value)
    check_saved_config(plain, source)
    return OmegaConf.create(plain)
