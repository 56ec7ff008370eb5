"""What nerfexp wrote into a folder, known by record: a file is replaced or removed only where it can be
shown to be one nerfexp wrote, never because of its name.

Each folder nerfexp writes into (a run directory; a report's folder, the run's own directory where the
report is of one run; a scene's folder) holds ``nerfexp-manifest.json``: every file nerfexp wrote there, by
its ``/``-separated path relative to the folder, with its size in bytes and its SHA-256, recorded as the
file is written (``record``). A file is nerfexp's while its size and SHA-256 equal its record; one without
a record, or changed since, is someone else's (``unproven``), and a command that would replace or remove
it refuses in one line naming it (``check_ours``). A missing file is always fine: nothing of it is lost.

The manifest is read, changed and written under an exclusive ``fcntl.flock`` of ``.nerfexp-manifest.lock``
beside it, so two commands writing into one run at once (``nerfexp-eval`` while ``nerfexp-view`` saves a
camera path) keep each other's records, and written atomically (``nerfexp.files.atomic_write``). It may
come from elsewhere with a run directory: it is read as data and bounded (``MANIFEST_BYTES``), and one that
cannot be read as a manifest proves nothing (every file it would prove is refused); the next record
starts it afresh.
"""

import contextlib
import fcntl
import json
import os
import stat
from collections.abc import Iterable, Iterator
from pathlib import Path

from nerfexp.errors import NerfexpError
from nerfexp.files import Staging, atomic_write, folder_entries, is_made, staged
from nerfexp.reading import UnreadableFile, parse_json, read_bytes, sha256

MANIFEST = "nerfexp-manifest.json"
LOCK = ".nerfexp-manifest.lock"  # flock'd around a change of the manifest (the manifest itself is renamed over)
BOOKKEEPING = (MANIFEST, LOCK)  # the manifest's own files: never a record of their own
MANIFEST_BYTES = 16 << 20  # a render of thousands of frames records a few hundred kB


def fingerprint(path: Path) -> dict | None:
    """``{"size": bytes, "sha256": hex}`` of the regular file ``path``; None where there is none (missing,
    or a link, a folder, a pipe: never followed or opened)."""
    try:
        found = os.lstat(path)
    except FileNotFoundError:
        return None
    if not stat.S_ISREG(found.st_mode):
        return None
    try:
        digest = sha256(path)
    except FileNotFoundError:  # removed since (a logger's file replaced as the run ends)
        return None
    return {"size": found.st_size, "sha256": digest}


def _is_record(record: object) -> bool:
    return (isinstance(record, dict) and type(record.get("size")) is int and record["size"] >= 0
            and isinstance(record.get("sha256"), str) and len(record["sha256"]) == 64
            and all(c in "0123456789abcdef" for c in record["sha256"]))


def read_records(root: Path) -> dict[str, dict]:
    """The records of ``root``'s manifest, ``{path: {"size", "sha256"}}``; none where it has no manifest.
    An ``UnreadableFile`` naming the manifest where it cannot be read as one (not a regular file, larger
    than ``MANIFEST_BYTES``, not JSON, or not the manifest's format)."""
    path = Path(root) / MANIFEST
    if not os.path.lexists(path):
        return {}
    if not path.is_file() or path.is_symlink():  # a pipe would block the read; a link points elsewhere
        raise UnreadableFile(path, "not a regular file")
    data = parse_json(read_bytes(path, MANIFEST_BYTES), str(path))
    files = data.get("files") if isinstance(data, dict) else None
    if not isinstance(files, dict) or not all(_is_record(record) for record in files.values()):
        raise UnreadableFile(path, 'not a nerfexp manifest (an object whose "files" maps each path to its '
                             '"size" and "sha256")')
    return files


@contextlib.contextmanager
def locked(root: Path) -> Iterator[None]:
    """Inside the block this process alone changes ``root``'s manifest (an exclusive ``flock`` of ``LOCK``,
    waited for)."""
    fd = os.open(Path(root) / LOCK, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


def record(root: Path, entries: Iterable[str], forget_under: str | None = None) -> None:
    """Record ``entries`` (``/``-separated paths relative to ``root``) in ``root``'s manifest as they are
    now: a regular file by its size and SHA-256; anything else (gone, a link) loses its record. Where
    ``forget_under`` names a folder, the records of files under it that are gone are dropped too. A
    manifest that cannot be read is started afresh: it proved nothing."""
    root = Path(root)
    with locked(root):
        try:
            records = read_records(root)
        except UnreadableFile:
            records = {}
        if forget_under is not None:
            entries = [*entries, *(entry for entry in records if entry.startswith(f"{forget_under}/"))]
        for entry in entries:
            if (found := fingerprint(root / entry)) is None:
                records.pop(entry, None)
            else:
                records[entry] = found
        atomic_write(root / MANIFEST, json.dumps({"files": dict(sorted(records.items()))}, indent=1).encode())


def write(root: Path, entry: str, data: bytes) -> None:
    """``data`` written to ``root/entry`` (``/``-separated, relative to ``root``) atomically
    (``nerfexp.files.atomic_write``), then recorded in ``root``'s manifest (``record``)."""
    atomic_write(Path(root) / entry, data)
    record(root, [entry])


@contextlib.contextmanager
def written_together(root: Path) -> Iterator[Staging]:
    """A ``nerfexp.files.Staging`` of ``root`` to fill (``nerfexp.files.staged``): once the block succeeds its files
    and folders are moved into place together and recorded in ``root``'s manifest (``record``; a folder's records
    replaced as a whole, ``record_folder``) before a SIGINT or SIGTERM takes effect, so that a command stopped at any
    moment leaves the set of files, and their records, all as they were or all new."""
    def recorded(staging: Staging) -> None:
        record(root, staging.files)
        for folder in staging.folders:
            record_folder(root, folder)

    with staged(root, recorded) as staging:
        yield staging


def folder_files(root: Path, folder: str) -> list[str]:
    """The files under ``root/folder`` (``folder``: relative to ``root``, ``/``-separated) as paths relative
    to ``root`` (``nerfexp.files.folder_entries``); ``[folder]`` where it is a file or a link, not a folder."""
    path = Path(root) / folder
    if os.path.lexists(path) and (path.is_symlink() or not path.is_dir()):
        return [folder]
    return [f"{folder}/{entry}" for entry in folder_entries(path)]


def record_folder(root: Path, folder: str) -> None:
    """Record every file under ``root/folder`` (``folder_files``), and forget the records of those under it
    that are gone (a folder replaced as a whole)."""
    record(root, folder_files(root, folder), forget_under=folder)


def record_matching(root: Path, patterns: tuple[str, ...]) -> None:
    """Record every file of ``root`` that is, or lies in a folder that is, matched by one of the ``fnmatch``
    ``patterns`` (``nerfexp.files.is_made``): what libraries wrote there under names nerfexp gave them."""
    record(root, [entry for entry in folder_entries(root) if is_made(entry, patterns)])


def unproven(root: Path, entries: Iterable[str]) -> list[str]:
    """Those of ``entries`` (relative to ``root``) that exist and are not files nerfexp wrote by ``root``'s
    manifest: without a record, or whose size or SHA-256 differs from it. An ``UnreadableFile`` where some
    exist and the manifest cannot be read (``read_records``)."""
    root = Path(root)
    present = [entry for entry in entries if os.path.lexists(root / entry)]
    if not present:
        return []
    records = read_records(root)

    def proven(entry: str) -> bool:
        wanted = records.get(entry)
        if wanted is None or os.lstat(root / entry).st_size != wanted["size"]:
            return False  # the size first: a changed file is told without reading it
        return fingerprint(root / entry) == wanted

    return [entry for entry in present if not proven(entry)]


def check_ours(root: Path, entries: Iterable[str], maker: str, advice: str) -> None:
    """A NerfexpError where one of ``entries`` (relative to ``root``) exists and is not a file ``maker`` (a
    command's name) wrote (``unproven``): one line naming them (three at most) and the manifest, then
    ``advice``, in which ``{it}`` reads "it" or "them"."""
    root = Path(root)
    entries = list(entries)
    try:
        foreign = unproven(root, entries)
    except UnreadableFile as error:
        present = [entry for entry in entries if os.path.lexists(root / entry)]
        raise NerfexpError(f"{error}, so nothing shows {_names(root, present)} to be {maker}'s: "
                           f"{advice.replace('{it}', 'it' if len(present) == 1 else 'them')}") from None
    if foreign:
        one = len(foreign) == 1
        raise NerfexpError(f"{_names(root, foreign)} {'is not a file' if one else 'are not files'} {maker} wrote "
                           f"({'it is' if one else 'they are'} not in {root / MANIFEST}, or changed since): "
                           f"{advice.replace('{it}', 'it' if one else 'them')}")


def _names(root: Path, entries: list[str]) -> str:
    shown = ", ".join(str(root / entry) for entry in entries[:3])
    return shown + (f" and {len(entries) - 3} more" if len(entries) > 3 else "")
