"""An ablation row means its label. A row of the paper's table (``conf/ablation/ROW.yaml``) chooses options of
config groups (``override /encoding: none``) and sets keys (``hierarchical``, ``data.n_train``,
``encoding.position.n_freqs``): the paper's axes. A run labelled with a row trains exactly that, or is refused
in one line before any work (``check_row``): a command-line or sweep override on one of the row's axes (a
group it chooses, a key under one, a key it sets), and a composed config that differs from the row on any of
them, would train another variant under the row's name.
"""

from collections.abc import Iterator, Mapping
from importlib.resources import files

import yaml
from omegaconf import DictConfig, OmegaConf

from nerfexp.domains import yaml_word
from nerfexp.errors import ConfigError

ROWS = "ablation"  # the config group of the paper's rows


def flat(node: Mapping, prefix: str = "") -> Iterator[tuple[str, object]]:
    """The leaves of the plain mapping ``node`` as (dotted key, value); a list is one leaf."""
    for key, value in node.items():
        if isinstance(value, Mapping):
            yield from flat(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value


def row_settings(row: str) -> tuple[dict[str, str], dict[str, object]]:
    """What the row ``row`` sets: ``({group: option}, {dotted key: value})``, read from its packaged file."""
    content = yaml.safe_load((files("nerfexp.conf") / ROWS / f"{row}.yaml").read_text())
    choices = {}
    for entry in content.pop("defaults", []):
        for key, option in entry.items():  # {"override /encoding": "posenc"}
            choices[key.split()[-1].lstrip("/")] = option
    return choices, dict(flat(content))


def on_axis(key: str, choices: dict[str, str], keys: dict[str, object]) -> bool:
    """Whether the dotted ``key`` is, or lies under, a group of ``choices`` or a key of ``keys``, or holds one."""
    return any(key == axis or key.startswith(f"{axis}.") or axis.startswith(f"{key}.") for axis in [*choices, *keys])


def check_row(cfg: DictConfig, chosen: Mapping, overrides: list[str]) -> None:
    """A ConfigError in one line where the run of ``cfg`` (its config groups' options ``chosen``, Hydra's
    ``runtime.choices``; its ``overrides`` from the command line or a sweep) is labelled with a row of
    ``ROWS`` and would train another variant than the row's (see the module's docstring)."""
    row = chosen.get(ROWS)
    if row is None:
        return
    choices, keys = row_settings(row)
    said = ", ".join([*(f"{g}={o}" for g, o in choices.items()), *(f"{k}={yaml_word(v)}" for k, v in keys.items())])
    advice = f"the row trains {said} (conf/{ROWS}/{row}.yaml), so its label would name another variant: drop one"
    for override in overrides:
        key, _, value = override.lstrip("+~").partition("=")
        axis = key in choices if key in chosen else on_axis(key, choices, keys)  # a group's option, or a key
        if key != ROWS and axis and choices.get(key) != value:
            raise ConfigError(f"{override} and {ROWS}={row}: {advice} of them")
    for group, option in choices.items():
        if chosen.get(group) != option:
            raise ConfigError(f"{ROWS}={row} with {group}={chosen.get(group)}: {advice} of them")
    for key, value in keys.items():
        if (now := OmegaConf.select(cfg, key)) != value:
            raise ConfigError(f"{ROWS}={row} with {key}={yaml_word(now)}: {advice} of them")
