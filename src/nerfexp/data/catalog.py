"""Scenes by name: the catalogue entries that ``data.scene=NAME`` finds, nerfexp's own (``catalog.yaml`` beside this
module) and a user's (``data.catalog=FILE``), read and checked; the cache that holds what they name is
``nerfexp.data.scene_cache``.

A catalogue is a YAML list of entries, each a mapping::

    - name: mylab/chair            # lowercase words of a-z 0-9 . _ - joined by '/'
      format: blender              # the data group it is read with (data=blender)
      url: https://host/chair.zip  # or a list of addresses, tried in order
      sha256: <64 hex digits>      # the archive's; null: none published (recorded on first download)
      path: chair                  # the scene's folder inside the archive
      size: 123456                 # optional: the archive's bytes (null: not known)
      sha256_from: ...             # optional: where the digest comes from, in words
      needs: {missing_images: skip}  # optional: data settings the scene as served needs
      note: ...                    # optional: what to know of the scene as served

A malformed file, entry or key is one ConfigError line naming the file, the entry and the key; so is a name given
twice, or a user's entry naming one of nerfexp's. A format is a ``data`` group of nerfexp's own that reads a scene
from a folder (its option file has a ``root`` key); an entry's format is checked against the chosen data group by
the class each builds (``format_target``), so that the class a run builds is the one the entry's scene is read with.
"""

import difflib
import functools
import re
from collections.abc import Mapping
from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path

import yaml

from nerfexp.domains import yaml_word
from nerfexp.downloads import is_web_address
from nerfexp.errors import ConfigError
from nerfexp.reading import YAML_PARSER, UnreadableFile, check_yaml_events, read_yaml_text

SHIPPED = "catalog.yaml"  # nerfexp's own entries, beside this module (docs/data.md lists them)
NAME = re.compile(r"[a-z0-9][a-z0-9._-]*(/[a-z0-9][a-z0-9._-]*)*")
NAME_LENGTH = 200  # characters: a name is also a file name in the cache (scene_cache.scene_folder)
SHA256 = re.compile(r"[0-9a-f]{64}")
SIZE_LIMIT = 1 << 44  # an archive's stated bytes: at most 16 TiB, beyond any file a download should be
TEXT_LENGTH = 1000  # characters of an entry's words (sha256_from, note)
REQUIRED = ("name", "format", "url", "sha256", "path")
OPTIONAL = ("size", "sha256_from", "needs", "note")
RECORDED = "none published: recorded on first download"  # an entry's sha256_from where its sha256 is null
SCENE_NAME = (f"a scene's name: lowercase words of a-z, 0-9, '.', '_', '-' joined by '/', at most {NAME_LENGTH} "
              "characters (nerfexp-data list names the scenes)",
              lambda v: isinstance(v, str) and len(v) <= NAME_LENGTH and NAME.fullmatch(v) is not None)


@dataclass(frozen=True)
class Entry:
    """A scene of a catalogue: its ``name``, the data group it is read with (``format``), the addresses of its
    archive (``urls``, tried in order), the archive's ``sha256`` (None: none published, recorded on first
    download) and ``size`` (None: not known), the scene's folder inside it (``path``), the data settings it needs
    (``needs``: (key, value) pairs), where its digest comes from (``sha256_from``), a ``note`` on the scene as
    served, and the catalogue it is from (``catalog``: a file, or nerfexp's own)."""

    name: str
    format: str
    urls: tuple[str, ...]
    sha256: str | None
    size: int | None
    path: str
    needs: tuple[tuple[str, object], ...]
    sha256_from: str
    note: str | None
    catalog: str


@functools.cache
def folder_formats() -> dict[str, str]:
    """{format: the class its data group builds}: the options of nerfexp's ``data`` group that read a scene from
    a folder (a ``root`` key), from their files."""
    found = {}
    for option in sorted((files("nerfexp.conf") / "data").iterdir(), key=lambda path: path.name):
        if option.name.endswith(".yaml"):
            content = yaml.safe_load(option.read_text()) or {}
            if "root" in content:
                found[option.name.removesuffix(".yaml")] = content["_target_"]
    return found


def format_target(format: str) -> str:
    """The class the data group ``format`` builds (``folder_formats``)."""
    return folder_formats()[format]


def is_text(value: object) -> bool:
    return isinstance(value, str) and 0 < len(value) <= TEXT_LENGTH and value.isprintable()


def is_folder(value: object) -> bool:
    """A folder inside an archive: ``/``-separated, relative, no ``..``."""
    return is_text(value) and not value.startswith("/") and ".." not in value.replace("\\", "/").split("/")


def is_setting(value: object) -> bool:
    """``needs``: a mapping of data settings (argument names) to plain values."""
    return isinstance(value, dict) and bool(value) and all(
        isinstance(k, str) and k.isidentifier() and (v is None or isinstance(v, str | int | float | bool))
        for k, v in value.items())


# key -> (what it must be, the test)
KEY_RULES = {
    "name": (SCENE_NAME[0], SCENE_NAME[1]),
    "format": (lambda: f"one of {', '.join(folder_formats())} (a data group that reads a folder)",
               lambda v: isinstance(v, str) and v in folder_formats()),
    "url": ("an http(s) address, or a non-empty list of them",
            lambda v: is_web_address(v) or (isinstance(v, list) and bool(v) and all(map(is_web_address, v)))),
    "sha256": ("64 lowercase hexadecimal digits (the archive's SHA-256), or null (none published: recorded on first "
               "download)", lambda v: v is None or (isinstance(v, str) and SHA256.fullmatch(v) is not None)),
    "path": ("the scene's folder inside the archive: a relative path without '..'", is_folder),
    "size": (f"the archive's bytes, a whole number in [1, 2^{SIZE_LIMIT.bit_length() - 1}], or null (not known)",
             lambda v: v is None or (isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= SIZE_LIMIT)),
    "sha256_from": (f"a line of at most {TEXT_LENGTH} characters", is_text),
    "needs": ("a mapping of data settings to values (e.g. {missing_images: skip})", is_setting),
    "note": (f"a line of at most {TEXT_LENGTH} characters", is_text),
}


def parse_entry(item: object, where: str, catalog: str) -> Entry:
    """The entry ``item`` of a catalogue (``where``: the file and its place there), checked key by key
    (``KEY_RULES``); a ConfigError naming ``where`` and the key otherwise."""
    if not isinstance(item, dict):
        raise ConfigError(f"{where}: expected a mapping with the keys {', '.join(REQUIRED)}, got {item!r:.80}")
    if isinstance(item.get("name"), str):
        where = f"{where} ({item['name']})"
    for key in REQUIRED:
        if key not in item:
            raise ConfigError(f"{where}: missing key '{key}' (an entry has {', '.join(REQUIRED)}; may have "
                              f"{', '.join(OPTIONAL)})")
    for key, value in item.items():
        if key not in KEY_RULES:
            close = difflib.get_close_matches(str(key), KEY_RULES, n=1)
            hint = f"; the closest: {close[0]}" if close else ""
            raise ConfigError(f"{where}: unknown key {key!r} (an entry has {', '.join(REQUIRED)}; may have "
                              f"{', '.join(OPTIONAL)}{hint})")
        wanted, test = KEY_RULES[key]
        if not test(value):
            raise ConfigError(f"{where}: '{key}': expected {wanted() if callable(wanted) else wanted}, "
                              f"got {value!r:.80}")
    urls = tuple(item["url"]) if isinstance(item["url"], list) else (item["url"],)
    sha256_from = item.get("sha256_from") or ("given by its catalogue" if item["sha256"] else RECORDED)
    return Entry(item["name"], item["format"], urls, item["sha256"], item.get("size"), item["path"],
                 tuple(sorted((item.get("needs") or {}).items())), sha256_from, item.get("note"), catalog)


def parse_catalog(content: object, where: str) -> list[Entry]:
    """The entries of a catalogue's parsed YAML ``content`` (from ``where``), each name once."""
    if not isinstance(content, list) or not content:
        raise ConfigError(f"{where}: expected a YAML list of scene entries (- name: ..., format: ..., url: ..., "
                          f"sha256: ..., path: ...), got {content!r:.80}")
    parsed, seen = [], set()
    for index, item in enumerate(content):
        entry = parse_entry(item, f"{where}: entry {index}", where)
        if entry.name in seen:
            raise ConfigError(f"{where}: entry {index}: the name {entry.name!r} is given twice")
        seen.add(entry.name)
        parsed.append(entry)
    return parsed


@functools.cache
def shipped() -> tuple[Entry, ...]:
    """nerfexp's own entries (``SHIPPED``)."""
    text = (files("nerfexp.data") / SHIPPED).read_text()
    where = f"nerfexp's {SHIPPED}"
    check_yaml_events(text, Path(where))
    return tuple(parse_catalog(yaml.load(text, Loader=YAML_PARSER), where))


def read_catalog(path: str | Path) -> list[Entry]:
    """A user's catalogue ``path`` (read bounded, without YAML aliases: ``nerfexp.reading``); a ConfigError naming
    it where it cannot be read or is malformed."""
    try:
        text = read_yaml_text(Path(path))
    except UnreadableFile as error:  # a file that is not there is named by the key that names it
        raise ConfigError(str(error) if Path(path).exists() else f"data.catalog={path}: {error.reason}") from None
    return parse_catalog(yaml.load(text, Loader=YAML_PARSER), str(path))


def catalog_entries(catalog: str | Path | None) -> dict[str, Entry]:
    """Every entry by name: nerfexp's, then those of the user's ``catalog`` (None: none); a ConfigError where a
    user's entry takes one of nerfexp's names."""
    found = {entry.name: entry for entry in shipped()}
    for entry in read_catalog(catalog) if catalog is not None else []:
        if entry.name in found:
            raise ConfigError(f"{catalog}: the name {entry.name!r} is one of nerfexp's own scenes (nerfexp-data "
                              "list): choose another")
        found[entry.name] = entry
    return found


def closest(name: str, names: list[str]) -> list[str]:
    """The names most like ``name``, best first (at most three)."""
    return difflib.get_close_matches(name, names, n=3, cutoff=0.5)


def unknown_name(name: str, known: Mapping[str, Entry], catalog: str | Path | None) -> str:
    """What is expected of ``name``, which no catalogue names, in words: the closest names."""
    near = closest(name, list(known))
    where = "nerfexp's catalogue" + (f" or {catalog}" if catalog is not None else "")
    return (f"a scene {where} names ({'the closest: ' + ', '.join(near) + '; ' if near else ''}"
            "nerfexp-data list names them all)")


def find_entry(name: str, catalog: str | Path | None) -> Entry:
    """The entry called ``name`` in nerfexp's catalogue or the user's ``catalog``; a ConfigError naming the
    closest names otherwise."""
    known = catalog_entries(catalog)
    if name not in known:
        raise ConfigError(f"scene {name}: expected {unknown_name(name, known, catalog)}")
    return known[name]


def scene_problem(config: Mapping) -> str | None:
    """What a scene's config (its arguments, with ``_target_``) needs where it names a scene (``scene``) and no
    folder (``root``), in words, or None: a name the catalogues hold, the class the entry's format builds, and the
    settings the entry needs (``needs``). A ConfigError for a malformed catalogue."""
    if config.get("root") is not None or config.get("scene") is None:
        return None
    known = catalog_entries(config.get("catalog"))
    entry = known.get(config["scene"])
    if entry is None:
        return unknown_name(config["scene"], known, config.get("catalog"))
    target = format_target(entry.format)
    if config.get("_target_") != target:
        return (f"data={entry.format} with it: the catalogue reads {entry.name} with data={entry.format} ({target}), "
                f"and this data builds {config.get('_target_')}")
    for key, value in entry.needs:
        if config.get(key) != value:
            return f"data.{key}={yaml_word(value)} with it: {entry.name} needs it ({entry.note or 'as served'})"
    return None
