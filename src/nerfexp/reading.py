"""Reading files that others may have made (run directories, sweeps, camera files, datasets) as data:
bounded in size and nesting, YAML without anchors or aliases, and every way a file can fail to read ending
in an ``UnreadableFile`` whose message names the file and what is wrong with it.

A file's whole text is read at once, so each kind of file has a size it may not exceed (``CONFIG_BYTES``:
a saved config or a sweep's ``multirun.yaml``; ``RECORD_BYTES``: a run's records and camera files),
refused before it is read. Within that size parsing is linear in the text, except what these readers
refuse: YAML anchors and aliases (a "billion laughs" file of a few lines expands to billions of nodes;
nerfexp's and Hydra's saved configs never use them) and nesting deeper than ``MAX_DEPTH`` (parsers
recurse).
"""

import hashlib
import json
import os
import stat
from pathlib import Path

import yaml

from nerfexp.errors import NerfexpError

CONFIG_BYTES = 1 << 20  # a saved config or multirun.yaml: a few kB as Hydra writes them
RECORD_BYTES = 64 << 20  # a run's results, status, metrics, evaluation; a camera path; a dataset's JSON
MAX_DEPTH = 64  # containers within containers: nerfexp's deepest configs nest about 8 levels
YAML_PARSER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # libyaml's where PyYAML was built with it


class UnreadableFile(NerfexpError):
    """A file that cannot be read as the data it should hold: ``PATH: REASON`` (``path``, ``reason``)."""

    def __init__(self, path: Path | str, reason: str):
        super().__init__(f"{path}: {reason}")
        self.path = path
        self.reason = reason


def name_problem(name: str) -> str | None:
    """Why the file path ``name`` (text from a file) can name no file, or None: a NUL byte (the system's calls end a
    name there), or characters the file system's encoding cannot write (a lone surrogate, which JSON's ``\\ud800``
    spells). Other limits (a name too long) are the file system's own: ``file_status`` meets them."""
    if "\0" in name:
        return "holds a NUL byte, which no file name can"
    try:
        os.fsencode(name)
    except UnicodeError as error:
        return f"holds characters no file name can ({error.reason} at character {error.start})"
    return None


def file_status(path: Path) -> os.stat_result | None:
    """``os.stat`` of ``path`` (links followed), or None where nothing is there (no such file, or a folder on its
    way missing or not a folder); an ``UnreadableFile`` naming it where it cannot be looked up: a name no file can
    have (``name_problem``), a name too long, a loop of links, a folder that may not be searched."""
    if (problem := name_problem(os.fspath(path))) is not None:
        raise UnreadableFile(ascii(os.fspath(path)), problem)
    try:
        return os.stat(path)
    except (FileNotFoundError, NotADirectoryError):
        return None
    except OSError as error:
        raise UnreadableFile(path, f"cannot be looked up ({error.strerror or error})") from None


def is_file(path: Path) -> bool:
    """Whether ``path`` is a regular file (links followed); an ``UnreadableFile`` where it cannot be looked up
    (``file_status``), where ``Path.is_file`` would raise or say False for a name no file can have."""
    status = file_status(path)
    return status is not None and stat.S_ISREG(status.st_mode)


def read_bytes(path: Path, limit: int) -> bytes:
    """The bytes of ``path``, refused (``UnreadableFile``) where it is not a regular file (a named pipe
    would block the reader, a device never end), holds more than ``limit`` bytes or cannot be read. At most
    ``limit + 1`` bytes are ever read, whatever the file claims its size is."""
    if (problem := name_problem(os.fspath(path))) is not None:
        raise UnreadableFile(ascii(os.fspath(path)), problem)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))  # a pipe opens without a writer
        with os.fdopen(fd, "rb") as file:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                raise UnreadableFile(path, "not a regular file")
            data = file.read(limit + 1)
    except OSError as error:
        raise UnreadableFile(path, f"cannot be read ({error.strerror or error})") from None
    if len(data) > limit:
        raise UnreadableFile(path, f"larger than the {limit:,} bytes nerfexp reads of such a file")
    return data


def sha256(path: Path) -> str:
    """The SHA-256 of the file ``path``'s bytes, hexadecimal, read in blocks of 1 MiB (a file of any size)."""
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def read_text(path: Path, limit: int) -> str:
    """``read_bytes`` of ``path`` decoded as UTF-8 (``UnreadableFile`` where it is not)."""
    try:
        return read_bytes(path, limit).decode("utf-8")
    except UnicodeDecodeError as error:
        raise UnreadableFile(path, f"not UTF-8 text ({error.reason} at byte {error.start})") from None


def check_yaml_events(text: str, path: Path) -> None:
    """An ``UnreadableFile`` where the YAML ``text`` (of ``path``) is not YAML, uses an anchor or an alias,
    or nests containers deeper than ``MAX_DEPTH``: checked on the parser's events, before any node is built."""
    depth = 0
    try:
        for event in yaml.parse(text, Loader=YAML_PARSER):
            if isinstance(event, yaml.AliasEvent) or getattr(event, "anchor", None) is not None:
                line = event.start_mark.line + 1 if event.start_mark is not None else "?"
                raise UnreadableFile(path, f"line {line}: a YAML anchor or alias, which nerfexp does not read "
                                     "(a few of them can expand into billions of values)")
            if isinstance(event, yaml.CollectionStartEvent):
                depth += 1
                if depth > MAX_DEPTH:
                    raise UnreadableFile(path, f"containers nested deeper than {MAX_DEPTH} levels")
            elif isinstance(event, yaml.CollectionEndEvent):
                depth -= 1
    except yaml.YAMLError as error:
        raise UnreadableFile(path, f"not YAML ({' '.join(str(error).split())})") from None


def read_yaml_text(path: Path, limit: int = CONFIG_BYTES) -> str:
    """The text of the YAML file ``path``, checked (``read_text``, ``check_yaml_events``), for a YAML
    reader to build: what it builds is then at most linear in the text's size."""
    text = read_text(path, limit)
    check_yaml_events(text, path)
    return text


def read_yaml(path: Path, limit: int = CONFIG_BYTES) -> object:
    """The YAML file ``path`` as plain Python data (``read_yaml_text``; YAML's safe types only)."""
    return yaml.load(read_yaml_text(path, limit), Loader=YAML_PARSER)


def parse_json(text: str | bytes, where: str) -> object:
    """``text`` parsed as JSON; an ``UnreadableFile`` naming ``where`` (a file, with a line where it is one
    of several) where it is not JSON or nests deeper than Python's parser recurses."""
    try:
        return json.loads(text)
    except json.JSONDecodeError as error:
        at = f"line {error.lineno}, column {error.colno}" if error.lineno > 1 or "\n" in error.doc else \
            f"column {error.colno}"
        raise UnreadableFile(where, f"not JSON ({at}: {error.msg})") from None
    except UnicodeDecodeError as error:
        raise UnreadableFile(where, f"not UTF-8 text ({error.reason} at byte {error.start})") from None
    except ValueError as error:  # e.g. an integer of more digits than Python converts
        raise UnreadableFile(where, f"not JSON nerfexp reads ({error})") from None
    except RecursionError:
        raise UnreadableFile(where, "JSON nested too deeply to read") from None


def read_json(path: Path, limit: int = RECORD_BYTES) -> object:
    """The JSON file ``path`` as Python data (``read_bytes``, ``parse_json``)."""
    return parse_json(read_bytes(path, limit), str(path))
