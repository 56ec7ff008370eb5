"""A config read from someone else's run directory is data: only the classes that nerfexp's own configs
build may be built from it.

Hydra builds whatever ``_target_`` a config names, so a crafted ``.hydra/config.yaml`` could call any
importable function (``torch.load`` of a pickle with ``weights_only: false``, say) the moment
``nerfexp-eval`` or ``nerfexp-render`` builds it. Before anything is built from a saved config, every
``_target_`` in it must be one of:

- a class defined in nerfexp (``nerfexp.*``, the class itself rather than something a module imported);
- ``lightning.Trainer``;
- a torch optimizer (a subclass of ``torch.optim.Optimizer`` from ``torch.optim``);
- a Lightning logger or callback (a subclass of ``Logger`` / ``Callback`` from
  ``lightning.pytorch.loggers`` / ``lightning.pytorch.callbacks``).

A config you compose yourself (``nerfexp ...`` with your overrides) is your own code, as in any Hydra
application, and is not checked.
"""

from collections.abc import Iterator
from pathlib import Path

from hydra.utils import get_class
from lightning.pytorch.callbacks import Callback
from lightning.pytorch.loggers import Logger
from omegaconf import DictConfig, OmegaConf
from torch.optim import Optimizer

from nerfexp.errors import ConfigError

TRAINERS = ("lightning.Trainer", "lightning.pytorch.Trainer")
FAMILIES = (("torch.optim.", Optimizer), ("lightning.pytorch.loggers.", Logger),
            ("lightning.pytorch.callbacks.", Callback))  # (where the target and its class live, their base)


def targets(node, path: str = "") -> Iterator[tuple[str, object]]:
    """Every ``_target_`` in a config's plain containers (``OmegaConf.to_container``): (its key, dotted,
    e.g. ``model.optimizer._target_``; its value)."""
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for key, value in items:
        dotted = f"{path}.{key}" if path else str(key)
        if key == "_target_":
            yield dotted, value
        else:
            yield from targets(value, dotted)


def buildable(target: object) -> bool:
    """Whether a saved config may build ``target`` (see the module's docstring). Only nerfexp's, torch's
    optimizers' and Lightning's own modules are imported to find out."""
    if not isinstance(target, str) or target in TRAINERS:
        return target in TRAINERS
    for prefix, base in (("nerfexp.", object), *FAMILIES):
        if target.startswith(prefix):
            try:
                cls = get_class(target)
            except (ImportError, ValueError):  # no such class (a function, a module, a missing name)
                return False
            return issubclass(cls, base) and cls.__module__.startswith(prefix)
    return False


def check_saved_config(cfg: DictConfig, source: Path) -> None:
    """A ConfigError naming the key and ``source`` (the file the config came from) for the first
    ``_target_`` that a saved config may not build (``buildable``); nothing is built or resolved."""
    for key, target in targets(OmegaConf.to_container(cfg, resolve=False)):
        if not buildable(target):
            raise ConfigError(
                f"{source}: {key}={target!r} is not a class nerfexp builds from a run's saved config (nerfexp's "
                "own classes, lightning.Trainer, torch optimizers, Lightning loggers and callbacks): a run "
                "directory from elsewhere is read as data, never run")
