"""Hydra's overrides (``KEY=VALUE``, ``+GROUP=OPTION``, a sweep's ``KEY=a,b``) read as what they would set, before
anything is composed: the checks that must see a sweep's every value before its first job (a config group's
options, ``nerfexp.settings.groups``; the labels, ``nerfexp.settings.checks.check_composition``) read them
through ``override_values``, one way."""

from collections.abc import Iterable, Iterator

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import ChoiceSweep, QuotedString
from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf


def unquoted(item: object) -> object:
    """A value of a choice sweep as its job gets it: a quoted text (``'a b'``) as its text, at any depth of the
    lists and mappings it holds (``[a],['b c']``)."""
    if isinstance(item, QuotedString):
        return item.text
    if isinstance(item, list):
        return [unquoted(x) for x in item]
    return {unquoted(k): unquoted(v) for k, v in item.items()} if isinstance(item, dict) else item


def chosen(value: object) -> list[object]:
    """What an override's parsed ``value`` would set, one value per job: each value of its choice sweep (``a,b``
    under -m; ``unquoted``), else ``value`` itself (a list is one value)."""
    return [unquoted(item) for item in value.list] if isinstance(value, ChoiceSweep) else [value]


def override_values(arguments: Iterable[str]) -> Iterator[tuple[str, str, list[object]]]:
    """``(argument, key, values)`` for each override among ``arguments`` (a command line's, or a run's
    ``hydra.overrides.task``) that sets something: its key or config group (``+``, ``++`` and a package
    ``@pkg`` aside: ``hydra/launcher``, ``scale.lr``) and what it would set (``chosen``). Options (``-m``),
    removals (``~KEY``) and an override that does not parse (Hydra's to say) are passed over."""
    for argument in arguments:
        if argument.startswith("-") or "=" not in argument:
            continue
        try:
            (override,) = OverridesParser.create().parse_overrides([argument])
        except HydraException:
            continue
        if not override.is_delete():
            yield argument, override.key_or_group, chosen(override.value())


def task_overrides(hydra: DictConfig) -> list[str]:
    """The overrides a run was composed with (``hydra.overrides.task``; ``hydra``: a composed config's ``hydra``
    section, or ``HydraConfig.get()``) as given: Hydra keeps them in its config, where reading an item resolves
    the interpolations in it (``notes=${oc.env:HOME}`` would read ``notes=/home/...``)."""
    return OmegaConf.to_container(hydra.overrides.task, resolve=False)
