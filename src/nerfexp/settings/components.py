"""The components of a composed config, as the settings check asks them (``nerfexp.domains``): each node with a
``_target_`` whose class declares its own settings (``nerfexp.settings.schema.component_class``), reachable from
what nerfexp builds (``ROOTS``) through its sections and the interpolations that carry one section into another
(``model.renderer.field.position_encoding: ${encoding.position}``), each once, under the key where it is set
(``encoding.position``), and never through an argument its parent's ``APPLIES`` says does nothing (the renderer's
``proposal`` with ``hierarchical=true``): a component that is not built is not asked.
"""

from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass

from omegaconf import DictConfig, OmegaConf

from nerfexp.config_keys import reference, source_key
from nerfexp.settings.schema import component_class

# What nerfexp builds or reads from a composed config: the sections its commands instantiate, and the top-level
# settings they read themselves
ROOTS = ("model", "datamodule", "trainer", "callbacks", "logger", "seed", "threads", "test_budgets", "resume", "tags",
         "notes")


@dataclass(frozen=True)
class Component:
    key: str  # where it is set: ``encoding.position``
    cls: type  # the class its ``_target_`` names
    config: Mapping  # its arguments, resolved, as plain data


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

    def visit(path: str) -> Iterator[Component]:
        key = source_key(cfg, path)
        node = OmegaConf.select(cfg, key, throw_on_resolution_failure=False)
        if key in seen or not isinstance(node, DictConfig):
            return
        seen.add(key)
        idle: set[str] = set()
        cls = component_class(node.get("_target_")) if "_target_" in node else None
        if cls is not None:
            config = OmegaConf.to_container(node, resolve=True)
            yield Component(key, cls, config)
            idle = idle_arguments(cls, config)
        written = OmegaConf.to_container(node, resolve=False)
        for name, raw in written.items():
            if name not in idle and (isinstance(raw, dict) or reference(raw) is not None):
                yield from visit(f"{key}.{name}")

    for root in ROOTS:
        if root in cfg:
            yield from visit(root)


def asked(cfg: DictConfig, attribute: str) -> Iterator[tuple[Component, object]]:
    """Each component of ``cfg`` (``components``) whose class declares ``attribute``, with it."""
    for component in components(cfg):
        if (declared := getattr(component.cls, attribute, None)) is not None:
            yield component, declared


def argument_keys(cfg: DictConfig, component: Component, arguments) -> list[str]:
    """The dotted keys of ``component``'s ``arguments`` (names, or dotted paths under its own sections), each
    where its section is set (``set_at``)."""
    return [set_at(cfg, f"{component.key}.{argument}") for argument in arguments]
