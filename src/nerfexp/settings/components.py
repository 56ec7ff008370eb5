"""The components of a composed config, as the settings check asks them (``nerfexp.domains``): each node with a
``_target_`` whose class declares its own settings (``nerfexp.settings.schema.component_class``), reachable from
what nerfexp builds (``ROOTS``) through its sections and the interpolations that carry one section into another
(``model.renderer.field.position_encoding: ${encoding.position}``), each once, under the key where it is set
(``encoding.position``), and never through an argument its parent's ``APPLIES`` says does nothing (the renderer's
``proposal`` with ``hierarchical=true``): a component that is not built is not asked.

A component's rules read its arguments as it is built with them (``Arguments``): those its config gives, and its
class's defaults for the others; one it needs and is not given is a ConfigError naming it, never a KeyError inside
a rule. ``argument_problem`` says where a component's config does not fit its class's signature at all (an argument
it needs and neither its config gives nor whatever builds it passes, an argument it does not take).
"""

import collections.abc
import functools
import inspect
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from types import UnionType
from typing import Union, get_args, get_origin, get_type_hints

from omegaconf import DictConfig, OmegaConf

from nerfexp.config_keys import reference, source_key
from nerfexp.errors import ConfigError
from nerfexp.settings.schema import component_class

# What nerfexp builds or reads from a composed config: the sections its commands instantiate, and the top-level
# settings they read themselves
ROOTS = ("model", "datamodule", "trainer", "callbacks", "logger", "seed", "threads", "test_budgets", "resume", "tags",
         "notes")


HYDRA_KEYS = ("_target_", "_partial_", "_args_", "_recursive_", "_convert_")  # Hydra's own keys of a section
POSITIONAL = (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
VARIADIC = (inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD)


@functools.cache
def parameters(cls: type) -> dict[str, inspect.Parameter]:
    """The parameters of ``cls``'s constructor, by name (none where Python cannot say)."""
    try:
        return dict(inspect.signature(cls).parameters)
    except (TypeError, ValueError):
        return {}


class Arguments(dict):
    """A component's arguments as its rules read them (``config`` in ``nerfexp.domains``): those its config gives,
    resolved, as plain data (``in`` and iteration see only these); reading one it does not give gives its class's
    default, what building it passes, and one without a default is a ConfigError naming the component's key
    (``sampler: ProposalSampler needs n_samples (not given)``)."""

    def __init__(self, given: Mapping, key: str, cls: type):
        super().__init__(given)
        self.key = key
        self.cls = cls

    def __missing__(self, name: str) -> object:
        parameter = parameters(self.cls).get(name)
        if parameter is not None and parameter.default is not inspect.Parameter.empty:
            return parameter.default
        raise ConfigError(f"{self.key}: {self.cls.__name__} needs {name} (not given)")


def arguments(cfg: DictConfig, key: str, cls: type, given: DictConfig | Mapping) -> Arguments:
    """The component at ``key`` of ``cfg`` (of class ``cls``; ``given``: its section, resolved here) as
    ``Arguments``, and so each section of it that is a component too (``HierarchyChoice``'s ``proposal``), named
    where it is set."""
    if isinstance(given, DictConfig):
        given = OmegaConf.to_container(given, resolve=True)
    inner = {}
    for name, value in given.items():
        inner_cls = component_class(value.get("_target_")) if isinstance(value, dict) else None
        inner[name] = value if inner_cls is None else arguments(cfg, source_key(cfg, f"{key}.{name}"), inner_cls, value)
    return Arguments(inner, key, cls)


def passed_by(taker: type | None, name: str) -> int | None:
    """How many positional arguments ``taker`` passes when it calls its argument ``name`` (a partial it builds), as
    its constructor's annotation says: ``Callable[[int], ViewDependence]``, 1; ``Callable[[], Sampler]`` (or one of
    a union), 0; None where it does not say (no taker, no annotation, ``Callable[..., X]``)."""
    try:  # an annotation Python cannot evaluate (a name imported only to type-check) says nothing
        hint = get_type_hints(taker.__init__).get(name) if taker is not None else None
    except Exception:  # noqa: BLE001 -- whatever evaluating it raised
        return None
    for candidate in get_args(hint) if get_origin(hint) in (Union, UnionType) else (hint,):
        if get_origin(candidate) is collections.abc.Callable:
            passed = get_args(candidate)[0]
            return None if passed is Ellipsis else len(passed)
    return None


@dataclass(frozen=True)
class Component:
    key: str  # where it is set: ``encoding.position``
    cls: type  # the class its ``_target_`` names
    config: Arguments  # its arguments, resolved, as plain data
    # the positional arguments whatever builds it passes: 0 where Hydra builds it whole, a partial's taker's
    # (``passed_by``); None where that is not said
    passed: int | None = 0


def set_at(cfg: DictConfig, key: str) -> str:
    """Where the section holding the dotted ``key`` is set: ``key`` with its section followed through the plain
    interpolations that carry one section into another (``model.renderer.proposal.n_samples`` ->
    ``proposal.n_samples``); the last part itself is not followed (``nerfexp.settings.checks.named`` says which
    key sets a value that comes from another)."""
    section, dot, last = key.rpartition(".")
    return f"{source_key(cfg, section)}{dot}{last}" if section else key


def idle_arguments(cls: type, config: Mapping) -> set[str]:
    """The arguments of a component of class ``cls`` (its resolved ``config``) that its ``APPLIES`` says do
    nothing."""
    return {argument for argument, applies in getattr(cls, "APPLIES", {}).items() if applies(config)}


# The walks of the configs being checked (``walked_once``): id -> [the config, its components or None: not walked yet]
_WALKS: dict[int, list] = {}


@contextmanager
def walked_once(cfg: DictConfig) -> Iterator[None]:
    """Within it, ``components(cfg)`` walks ``cfg`` once, at its first call, and gives the same components after
    (the settings check asks the components many times and changes nothing of the config). Inside another for the
    same ``cfg`` it keeps that one's walk, and leaves it to that one to end."""
    held = _WALKS.get(id(cfg))
    if held is not None and held[0] is cfg:
        yield
        return
    _WALKS[id(cfg)] = [cfg, None]
    try:
        yield
    finally:
        _WALKS.pop(id(cfg), None)


def components(cfg: DictConfig) -> Iterator[Component]:
    """Each component of ``cfg`` that nerfexp builds, once, where it is set, in the order the config holds them
    (see the module's docstring); walked once where ``walked_once`` holds ``cfg``."""
    held = _WALKS.get(id(cfg))
    if held is None or held[0] is not cfg:
        return walk(cfg)
    if held[1] is None:
        held[1] = list(walk(cfg))  # an error on the way is raised here, at the first ask, as without the cache
    return iter(held[1])


def walk(cfg: DictConfig) -> Iterator[Component]:
    """``components``' walk of ``cfg``, done anew."""
    seen: set[str] = set()

    def visit(path: str, taker: type | None) -> Iterator[Component]:
        key = source_key(cfg, path)
        node = OmegaConf.select(cfg, key, throw_on_resolution_failure=False)
        if key in seen or not isinstance(node, DictConfig):
            return
        seen.add(key)
        idle: set[str] = set()
        cls = component_class(node.get("_target_")) if "_target_" in node else None
        if cls is not None:
            config = arguments(cfg, key, cls, node)
            passed = passed_by(taker, path.rpartition(".")[2]) if node.get("_partial_", False) else 0
            yield Component(key, cls, config, passed)
            idle = idle_arguments(cls, config)
        written = OmegaConf.to_container(node, resolve=False)
        for name, raw in written.items():
            if name not in idle and (isinstance(raw, dict) or reference(raw) is not None):
                yield from visit(f"{key}.{name}", cls)

    for root in ROOTS:
        if root in cfg:
            yield from visit(root, None)


def asked(cfg: DictConfig, attribute: str) -> Iterator[tuple[Component, object]]:
    """Each component of ``cfg`` (``components``) whose class declares ``attribute``, with it."""
    for component in components(cfg):
        if (declared := getattr(component.cls, attribute, None)) is not None:
            yield component, declared


def argument_keys(cfg: DictConfig, component: Component, arguments) -> list[str]:
    """The dotted keys of ``component``'s ``arguments`` (names, or dotted paths under its own sections), each
    where its section is set (``set_at``)."""
    return [set_at(cfg, f"{component.key}.{argument}") for argument in arguments]


def argument_problem(component: Component) -> str | None:
    """Where ``component``'s config does not fit its class's constructor, what is wrong, naming the key: an argument
    it needs (no default) that neither its config gives nor whatever builds it passes (``Component.passed``: the
    first positional ones; not asked where that is not said), or one its config gives that it does not take; None
    where it fits."""
    taken, given = parameters(component.cls), component.config
    if not taken:
        return None
    name = component.cls.__name__
    if not any(parameter.kind == inspect.Parameter.VAR_KEYWORD for parameter in taken.values()):
        unknown = [argument for argument in given if argument not in taken and argument not in HYDRA_KEYS]
        if unknown:
            return (f"{component.key}.{unknown[0]}: {name} takes no argument {unknown[0]} "
                    f"(it takes {', '.join(n for n, p in taken.items() if p.kind not in VARIADIC)})")
    if component.passed is None:
        return None
    positional = [n for n, p in taken.items() if p.kind in POSITIONAL]
    passed = set(positional[:component.passed + len(given.get("_args_", []))])
    needed = [n for n, p in taken.items() if p.default is inspect.Parameter.empty and p.kind not in VARIADIC
              and n not in given and n not in passed]
    return f"{component.key}: {name} needs {', '.join(needed)} (not given)" if needed else None
