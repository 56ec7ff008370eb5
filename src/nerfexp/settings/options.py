"""The options of nerfexp's config groups as their files write them (``conf/GROUP/OPTION.yaml``, read as YAML,
unresolved): which options read a key (``options_reading``), or pass any other test of their content. The settings
check asks them of a key the composed config leaves unread: a size no chosen option reads is a setting still
(``nerfexp.settings.schema``), and an override of it names the options that would read it
(``nerfexp.settings.unused``)."""

import functools
import io
from collections.abc import Callable
from importlib.resources import files

from omegaconf import OmegaConf

from nerfexp.config_keys import entries, readers, reference


@functools.cache
def option_files() -> tuple[tuple[str, str, dict], ...]:
    """Every option of nerfexp's config groups, read as YAML, unresolved: (group, option, its plain content)."""
    found = []
    for folder in sorted(files("nerfexp.conf").iterdir(), key=lambda path: path.name):
        if folder.is_dir():
            for option in sorted(folder.iterdir(), key=lambda path: path.name):
                if option.name.endswith(".yaml"):
                    content = OmegaConf.to_container(OmegaConf.load(io.StringIO(option.read_text())), resolve=False)
                    found.append((folder.name, option.name.removesuffix(".yaml"), content or {}))
    return tuple(found)


def options_where(test: Callable[[dict], bool]) -> dict[str, list[str]]:
    """The options whose content passes ``test``: {group: [option, ...]}."""
    found: dict[str, list[str]] = {}
    for group, option, content in option_files():
        if test(content):
            found.setdefault(group, []).append(option)
    return found


@functools.cache
def primary_readers(key: str) -> tuple[str, ...]:
    """The keys of nerfexp's own ``config.yaml``, as it writes them, that read ``key`` through a plain reference
    (``model.chunk: ${scale.chunk}``): where a run overrides such a key, ``key`` is read by no one in that run
    and is still a setting, whose rule is the one of the keys nerfexp's config would have it set."""
    content = OmegaConf.to_container(OmegaConf.load(io.StringIO((files("nerfexp.conf") / "config.yaml").read_text())),
                                     resolve=False)
    return tuple(readers({k: v for k, v in content.items() if k != "defaults"}).get(key, []))


@functools.cache
def options_reading(key: str) -> dict[str, list[str]]:
    """The options of nerfexp's config groups whose file reads ``key`` (a value ``${key}``): {group: [option, ...]}."""
    return options_where(lambda content: any(reference(value) == key for _, value in entries(content)))
