"""The scene cache: the scenes a catalogue names (``nerfexp.data.catalog``) downloaded once, verified, unpacked, and
found again by name with no network access.

Where: ``$NERFEXP_DATA``, else ``$XDG_CACHE_HOME/nerfexp/data`` (``~/.cache/nerfexp/data``). Its layout::

    archives/SHA256       archives whose bytes were verified, named by their SHA-256
    checksums/KEY.json    a source without a published digest: its first download's SHA-256 and size (KEY: the start
                          of the SHA-256 of the entry's first address)
    scenes/NAME/          a scene, unpacked (NAME with '/' as '+'): what data.root is for a scene by name
    scenes/NAME.json      its record (``SCENE_KEYS``): the name, the source, the archive's SHA-256 and size, how that
                          digest was established (pinned, or recorded on first download) and when, the folder
    downloads/KEY.part    a download under way, or one a signal or a killed process left (the next one continues it)

A fetch (``fetch_scene``) holds an ``flock`` of the cache's folder, so that the jobs of a sweep take turns (the
system releases it when its process ends, however it ends), and:

1. answers with the scene in the cache where its record is there and of the digest the entry pins (or the cache
   recorded for its source), with no network access at all;
2. else takes the archive: the cache's own of that digest (hashed again before it is opened), else downloads it from
   each of the entry's addresses in turn (``data.mirror``'s host in place of theirs, ``nerfexp.downloads``) into
   downloads/, checked against the entry's size and its pinned or recorded SHA-256: a mismatch names both digests;
3. unpacks the scene's folder from it into a new folder beside scenes/NAME (``nerfexp.data.archives``: members that
   would leave it, links and oversized members refused before anything is written);
4. only then commits: the folder renamed to scenes/NAME, the archive moved to archives/, a first download's digest
   recorded, and last the scene's record, without which a folder is not a scene of the cache.

A failure before step 4 (no network, an HTTP status, a checksum or size mismatch, an archive refused, a full disk)
removes what the fetch made and says in one line what failed: the cache is as it was. Nothing is unpacked from bytes
whose SHA-256 is not the one pinned or recorded, and a scene's folder is only ever one whole unpacked folder.
"""

import contextlib
import errno
import fcntl
import hashlib
import json
import logging
import os
import time
from collections.abc import Iterator
from pathlib import Path

from nerfexp.data.archives import TOTAL_BYTES, unpack_folder
from nerfexp.data.catalog import SHA256, Entry
from nerfexp.downloads import DownloadFailed, download, mirrored
from nerfexp.errors import DatasetError
from nerfexp.files import atomic_directory, atomic_write
from nerfexp.reading import UnreadableFile, read_json, sha256

CACHE_VARIABLE = "NERFEXP_DATA"  # the cache's folder, where set
ARCHIVE_BYTES = TOTAL_BYTES  # an archive of unknown size is downloaded up to this many bytes
RECORD_BYTES = 64 << 10  # a record is a few hundred bytes
PINNED, RECORDED = "pinned", "recorded on first download"  # how an archive's digest was established
SCENE_KEYS = ("name", "catalog", "url", "downloaded_from", "path", "sha256", "size", "checksum", "sha256_from",
              "recorded", "unpacked", "folder")
DISK_FULL = (errno.ENOSPC, errno.EDQUOT)

log = logging.getLogger(__name__)


def data_cache() -> Path:
    """The cache's folder, absolute: ``NERFEXP_DATA``, else ``$XDG_CACHE_HOME/nerfexp/data``
    (``~/.cache/nerfexp/data``)."""
    if os.environ.get(CACHE_VARIABLE):
        return Path(os.path.abspath(os.path.expanduser(os.environ[CACHE_VARIABLE])))
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache").absolute() / "nerfexp" / "data"


def source_key(entry: Entry) -> str:
    """The name of ``entry``'s source in the cache: the first 16 hex digits of the SHA-256 of its first address."""
    return hashlib.sha256(entry.urls[0].encode()).hexdigest()[:16]


def scene_folder(cache: Path, name: str) -> Path:
    """Where the scene ``name`` is unpacked: ``scenes/NAME`` with '/' as '+' (a name is never a folder of another)."""
    return cache / "scenes" / name.replace("/", "+")


def scene_record_path(cache: Path, name: str) -> Path:
    folder = scene_folder(cache, name)
    return folder.with_name(f"{folder.name}.json")


def checksum_path(cache: Path, entry: Entry) -> Path:
    return cache / "checksums" / f"{source_key(entry)}.json"


def now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def recorded_checksum(cache: Path, entry: Entry) -> dict | None:
    """The digest the cache recorded for ``entry``'s source on its first download (``{url, sha256, size,
    recorded}``), or None where it recorded none; a DatasetError naming the file where it is not such a record
    (a record that cannot be read is never taken for no record: that would let the next download set the digest)."""
    path = checksum_path(cache, entry)
    if not path.exists():
        return None
    try:
        record = read_json(path, RECORD_BYTES)
    except UnreadableFile as error:
        record = error
    if (not isinstance(record, dict) or not isinstance(record.get("sha256"), str)
            or SHA256.fullmatch(record["sha256"]) is None or record.get("url") != entry.urls[0]
            or not isinstance(record.get("size"), int) or not isinstance(record.get("recorded"), str)):
        raise DatasetError(f"{path}: not the digest nerfexp recorded for {entry.urls[0]} ({str(record):.80}): remove "
                           "it, and the next download's digest is recorded again")
    return record


def expected_checksum(cache: Path, entry: Entry) -> tuple[str | None, int | None, str]:
    """The SHA-256 and size ``entry``'s archive must have, and where they come from in words: pinned by the
    catalogue, recorded by the cache on its first download, or neither yet (None: this download's are recorded)."""
    if entry.sha256 is not None:
        return entry.sha256, entry.size, f"{PINNED}: {entry.sha256_from}"
    record = recorded_checksum(cache, entry)
    if record is None:
        return None, entry.size, f"{RECORDED}: none yet"
    return record["sha256"], record["size"], f"{RECORDED} on {record['recorded']} ({checksum_path(cache, entry)})"


def scene_record(cache: Path, entry: Entry) -> dict | None:
    """The record of ``entry``'s scene in the cache where it is whole (its record and folder there) and of the
    archive the entry expects (``expected_checksum``), else None. Nothing is downloaded."""
    path = scene_record_path(cache, entry.name)
    try:
        record = read_json(path, RECORD_BYTES)
    except UnreadableFile:  # none (or not nerfexp's): not a scene of the cache, fetched again
        return None
    if not isinstance(record, dict) or set(record) != set(SCENE_KEYS) or record["name"] != entry.name:
        return None
    expected = expected_checksum(cache, entry)[0]
    if (expected is not None and record["sha256"] != expected) or record["path"] != entry.path:
        log.info("scene %s in the cache was unpacked from another archive (SHA-256 %s) or folder: fetched again",
                 entry.name, record["sha256"])
        return None
    if not scene_folder(cache, entry.name).is_dir():
        return None
    return record


def cached_folder(entry: Entry, cache: Path | None = None) -> Path:
    """The folder of ``entry``'s scene in the cache (``scene_record``), with no network access; a DatasetError
    saying how to fetch it where it is not there."""
    cache = data_cache() if cache is None else cache
    if scene_record(cache, entry) is None:
        raise DatasetError(f"data.scene={entry.name}: not in the scene cache {cache} (nerfexp downloads it when it "
                           f"trains; nerfexp-data fetch {entry.name} does now)")
    return scene_folder(cache, entry.name)


@contextlib.contextmanager
def cache_lock(cache: Path) -> Iterator[None]:
    """Inside the block this process alone fetches into ``cache``: an exclusive ``flock`` of its folder (no file
    is made for it), released by the system when the process ends, however it ends. A wait says so, once."""
    fd = os.open(cache, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            log.info("waiting for another nerfexp process fetching into %s", cache)
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


def downloaded(entry: Entry, mirror: str | None, partial: Path, expected: str | None, size: int | None,
               how: str) -> tuple[str, str]:
    """``entry``'s archive downloaded into ``partial`` from the first of its addresses (through ``mirror``) that
    serves the bytes expected (``expected``: the SHA-256, None: any; ``size``: None, any up to ``ARCHIVE_BYTES``;
    ``how``: where the digest comes from): the address and the digest. A DatasetError saying what failed at each
    address otherwise, ``partial`` removed."""
    failures = []
    for url in entry.urls:
        address = mirrored(url, mirror)
        continued = partial.is_file() and partial.stat().st_size > 0  # a download a signal or a kill left
        log.info("scene %s: downloading %s into %s%s", entry.name, address, partial.parent.parent,
                 ", continuing the download left there" if continued else "")
        try:
            digest = download(address, partial, size, ARCHIVE_BYTES, entry.name)
        except DownloadFailed as error:
            failures.append(f"{address}: {error}")
        else:
            if expected is None or digest == expected:
                return address, digest
            if continued:  # the bytes left there were not the start of this file: once more, from the first byte
                partial.unlink()
                return downloaded(entry, mirror, partial, expected, size, how)
            failures.append(f"{address}: checksum mismatch: its SHA-256 is {digest}, expected {expected} ({how})")
        partial.unlink(missing_ok=True)
    raise DatasetError(f"scene {entry.name}: {'; '.join(failures)}: nothing of it kept in {partial.parent.parent}")


def fetch_scene(entry: Entry, mirror: str | None = None, cache: Path | None = None) -> dict:
    """``entry``'s scene in the cache (``cache``, None: ``data_cache()``): found there, else downloaded, verified
    and unpacked (the module's docstring); its record. A DatasetError in one line saying what failed (a full disk
    included), with the cache as it was."""
    cache = data_cache() if cache is None else cache
    cache.mkdir(parents=True, exist_ok=True)
    with cache_lock(cache):
        record = scene_record(cache, entry)
        if record is not None:
            log.info("scene %s: in the cache, %s (its archive's SHA-256 %s, %s)", entry.name, record["folder"],
                     record["sha256"], record["checksum"])
            return record
        try:
            return fetch(entry, mirror, cache)
        except OSError as error:
            if error.errno not in DISK_FULL:
                raise
            raise DatasetError(f"scene {entry.name}: no space left on the disk of {cache} "
                               f"({error.strerror or error}): the cache is as it was") from None


def fetch(entry: Entry, mirror: str | None, cache: Path) -> dict:
    """``fetch_scene``'s steps 2 to 4, under its lock."""
    expected, size, how = expected_checksum(cache, entry)
    archive = cache / "archives" / expected if expected is not None else None
    partial = cache / "downloads" / f"{source_key(entry)}.part"
    url = None  # where the archive was downloaded from: none where the cache held it
    if archive is not None and archive.is_file() and sha256(archive) != expected:  # hashed again before it is opened
        log.warning("%s is not the archive its name says (a changed or damaged file): downloading it again", archive)
        archive = None
    try:
        if archive is None or not archive.is_file():
            partial.parent.mkdir(exist_ok=True)
            url, digest = downloaded(entry, mirror, partial, expected, size, how)
            archive = partial
        else:
            digest = expected
        folder = scene_folder(cache, entry.name)
        with atomic_directory(folder, replace=True) as new:
            label = f"scene {entry.name}: the archive {url or archive}"
            total = unpack_folder(archive, entry.path, new, label=label)
    except BaseException as error:
        if not isinstance(error, Exception):  # a signal: the download stays, for the next fetch to continue
            raise
        partial.unlink(missing_ok=True)
        raise
    return committed(entry, cache, archive, digest, url, how, total)


def committed(entry: Entry, cache: Path, archive: Path, digest: str, url: str | None, how: str, total: int) -> dict:
    """Step 4 of ``fetch_scene``: ``archive`` (the download, or the cache's own) kept as ``archives/DIGEST``, the
    digest recorded where it is the source's first, and the scene's record written; the record."""
    size = archive.stat().st_size
    kept = cache / "archives" / digest
    if archive != kept:
        kept.parent.mkdir(exist_ok=True)
        os.replace(archive, kept)
    checksum = PINNED if entry.sha256 is not None else RECORDED
    recorded = now()
    if entry.sha256 is None:
        record = recorded_checksum(cache, entry)
        if record is None:
            atomic_write(checksum_path(cache, entry), json.dumps(
                {"url": entry.urls[0], "sha256": digest, "size": size, "recorded": recorded}, indent=1).encode())
            log.warning("scene %s: no SHA-256 is published for %s: this first download's, %s, is recorded in %s, and "
                        "every later download must match it", entry.name, entry.urls[0], digest,
                        checksum_path(cache, entry))
        else:
            recorded = record["recorded"]
    record = {"name": entry.name, "catalog": entry.catalog, "url": entry.urls[0], "downloaded_from": url,
              "path": entry.path, "sha256": digest, "size": size, "checksum": checksum,
              "sha256_from": entry.sha256_from, "recorded": recorded, "unpacked": now(),
              "folder": str(scene_folder(cache, entry.name))}
    atomic_write(scene_record_path(cache, entry.name), json.dumps(record, indent=1).encode())
    log.info("scene %s: %s bytes unpacked into %s from an archive of SHA-256 %s (%s)", entry.name, f"{total:,}",
             scene_folder(cache, entry.name), digest, how if entry.sha256 is not None else checksum)
    return record

