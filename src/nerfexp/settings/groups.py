"""A config group's value is one of its options, by name. Hydra composes more than that, and records what it
composed wrongly: a list (``experiment=[fast]``) loads each of the group's configs it names and records no choice
for the group at all (``hydra.runtime.choices`` leaves it out: experiment None), and a path
(``experiment=../ablation/no_posenc``, ``./fast``) loads a config from wherever it leads, another group's
included, and records the path as the group's choice (a row of the paper's table trained as a preset, which
the row check and the report do not know as that row). So anything but one option's name is refused in one
line naming the group, the value and the group's options, before any work:

- on the command line (``check_group_overrides``), before Hydra composes anything (a path may not compose, and
  a sweep's values are composed only in its jobs): what each override of a group would choose (its value, or
  each value of its sweep) is a name, never ``null``, a number, a mapping, a range, a list or a path;
- in the composed config (``check_group_values``), for a single run before its directory is made, for a sweep
  before its directory is made and again in each job: the same for ``hydra.overrides.task`` (a job's are the
  sweeper's values); each choice in ``hydra.runtime.choices`` (from the command line, an appended ``+group=``,
  a config file's defaults list, a ``${...}`` in one) one of the options Hydra finds for its group in the config
  sources the run was composed from (``hydra.runtime.config_sources``: nerfexp's ``conf/``, Hydra's and its
  plugins', a folder on ``hydra.searchpath``); and each group of ``config.yaml``'s defaults list has a choice
  (none: a config file's defaults list gave it a list), unless ``~GROUP`` removed it. A group that the defaults list
  chooses from other groups' choices (``derived_choices``) is no one's to choose, and is not checked.
"""

from collections.abc import Callable, Iterable, Mapping
from importlib.resources import files

import yaml
from hydra._internal.config_repository import ConfigRepository
from hydra._internal.config_search_path_impl import ConfigSearchPathImpl
from hydra.core.object_type import ObjectType
from hydra.core.override_parser.types import Glob
from omegaconf import DictConfig

from nerfexp.errors import ConfigError
from nerfexp.settings.overrides import override_values, task_overrides

HYDRA_GROUPS = "hydra/"  # Hydra's own groups: their options are Hydra's and its plugins' as well as nerfexp's


def derived_choices() -> dict[str, str]:
    """{group@package as ``hydra.runtime.choices`` records it: its folder} of the groups ``config.yaml``'s defaults
    list chooses from other groups' choices (``optional acceleration/by_encoding@acceleration.grid:
    ${acceleration}_${encoding}``: the grid's settings for the encoding): no one chooses them, and the option they
    name need not exist (``optional``: none is merged then)."""
    defaults = yaml.safe_load((files("nerfexp.conf") / "config.yaml").read_text())["defaults"]
    return {group.removeprefix("optional "): group.removeprefix("optional ").partition("@")[0]
            for entry in defaults if isinstance(entry, dict) for group, option in entry.items()
            if group.startswith("optional ") and isinstance(option, str) and "${" in option}


def nerfexp_groups() -> set[str]:
    """The config groups of nerfexp's own ``conf/`` that a run chooses an option of: each folder, nested ones by
    their path (``encoding/hashgrid_sizes``, ``hydra/launcher``), those chosen from other groups' choices
    (``derived_choices``) aside."""
    derived = set(derived_choices().values())
    return {group for group in config_folders() if group not in derived}


def config_folders() -> set[str]:
    """Every folder of nerfexp's own ``conf/``, nested ones by their path."""
    found, pending = set(), [(files("nerfexp.conf"), "")]
    while pending:
        folder, group = pending.pop()
        for item in folder.iterdir():
            if item.is_dir() and not item.name.startswith("__"):
                name = f"{group}/{item.name}" if group else item.name
                found.add(name)
                pending.append((item, name))
    return found


def nerfexp_options(group: str) -> list[str]:
    """The options nerfexp's own ``conf/`` holds for the config group ``group`` (its folder's YAML files); none
    for a group of Hydra's (``hydra/launcher``: Hydra and its plugins have options nerfexp's folder lacks) or one
    nerfexp does not have."""
    if group.startswith(HYDRA_GROUPS) or group not in nerfexp_groups():
        return []
    folder = files("nerfexp.conf").joinpath(*group.split("/"))
    return sorted(path.name.removesuffix(".yaml") for path in folder.iterdir() if path.name.endswith(".yaml"))


def default_choices() -> dict[str, str | None]:
    """{group: its option, or None} of ``config.yaml``'s defaults list (Hydra's own groups aside)."""
    defaults = yaml.safe_load((files("nerfexp.conf") / "config.yaml").read_text())["defaults"]
    return {group: option for entry in defaults if isinstance(entry, dict) for group, option in entry.items()
            if " " not in group}  # "override hydra/help": Hydra's


def unchosen_groups() -> set[str]:
    """The config groups ``config.yaml``'s defaults leave without an option (``experiment: null``)."""
    return {group for group, option in default_choices().items() if option is None}


def not_a_name(item: object) -> str | None:
    """Why ``item``, one value a group is given, is not one option's name, in words after the refusal ("" where
    the refusal says it all: null, a number, a mapping, a range); None for a name (or a glob, which chooses among
    the group's own options). A path is a text that Hydra would read as one: with a ``/``, or ``.``, ``..``."""
    if isinstance(item, Glob):
        return None
    if isinstance(item, list):
        return "; a list is not one (Hydra would compose each config it names and record no choice)"
    if not isinstance(item, str):
        return ""
    if "/" in item or item in ("", ".", ".."):
        return "; a path is not one (Hydra would compose whatever config it leads to, in another group too)"
    return None


def refusal(argument: str, group: str, item: object, options: list[str]) -> ConfigError:
    """The one line refusing ``argument`` (``GROUP=VALUE`` as given), which gives ``group``, whose options are
    ``options``, ``item`` (``not_a_name`` says why)."""
    listed = f" (choose from {', '.join(options)})" if options else ""
    none = f"; none is {group}'s default: leave it out for none" if item is None and group in unchosen_groups() else ""
    return ConfigError(f"{argument}: a config group takes an option's name{listed}{none}{not_a_name(item) or ''}")


def check_group_overrides(arguments: Iterable[str], is_group: Callable[[str], bool],
                          options: Callable[[str], list[str]] = nerfexp_options) -> None:
    """A ConfigError where a command-line argument or override of ``arguments`` gives a config group (a key that
    ``is_group``, or one with a ``/``: ``hydra/launcher``) what is not one option's name (``not_a_name``), naming
    the group's ``options``: ``null`` (refused rather than read as no option: a group that has none by default,
    ``experiment``, is left out of the command line for none), a number, a boolean, a mapping, a range, a list
    or a path (``nerfexp.settings.overrides.override_values``: options such as ``-m``, removals ``~GROUP`` and an
    override that does not parse, Hydra's to say, are passed over)."""
    for argument, group, values in override_values(arguments):
        if "/" in group or is_group(group):
            for item in values:
                if not_a_name(item) is not None:
                    raise refusal(argument, group, item, options(group))


def is_nerfexp_group(key: str) -> bool:
    """Whether ``key`` is a config group of nerfexp's own ``conf/`` (``nerfexp_groups``)."""
    return key in nerfexp_groups()


def repository_of(sources: Iterable[Mapping]) -> ConfigRepository:
    """Hydra's repository of the config sources ``sources`` (``hydra.runtime.config_sources``: those a run was
    composed from, each its provider, scheme and path), which finds a group's options in any of them."""
    search_path = ConfigSearchPathImpl()
    for source in sources:
        search_path.append(source["provider"], f"{source['schema']}://{source['path']}")
    return ConfigRepository(search_path)


def check_group_values(hydra: DictConfig) -> None:
    """A ConfigError where the run that ``hydra`` (a composed config's ``hydra`` section, or ``HydraConfig.get()``)
    describes gives a config group what is not one option's name: an override of ``hydra.overrides.task`` as
    ``check_group_overrides`` has it, or a choice of ``hydra.runtime.choices`` that is not one of the options of
    its group in the config sources the run was composed from (``repository_of``). A group left without an
    option (``experiment: null`` in ``config.yaml``) is none's, not a choice; a group of ``config.yaml``'s defaults
    that the choices leave out, and no ``~GROUP`` removed, was given a list in a config file's defaults list."""
    repository = repository_of(hydra.runtime.config_sources)

    def options(group: str) -> list[str]:
        return repository.get_group_options(group, results_filter=ObjectType.CONFIG)

    overrides = task_overrides(hydra)
    check_group_overrides(overrides, repository.group_exists, options)
    choices = hydra.runtime.choices
    derived = derived_choices()
    for group, option in choices.items():
        if option is not None and group not in derived and option not in options(group):
            raise refusal(f"{group}={option}", group, option, options(group))
    removed = {argument.lstrip("~").partition("=")[0] for argument in overrides if argument.startswith("~")}
    for group in default_choices():
        if group not in choices and group not in removed:  # a list in a config's defaults list: no choice recorded
            raise refusal(f"{group}=[...] in a config's defaults list", group, [], options(group))
