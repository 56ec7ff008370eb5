"""The scene cache (nerfexp.data.scene_cache): a scene by name is downloaded once from a server on 127.0.0.1 (the
entry's host replaced by the mirror), verified, unpacked and recorded, then found again with no network access; a
download that breaks off continues where it stopped (or from the start, where the server ignores Range); and every
failure (a changed byte, a wrong size, a member that escapes, an oversized one, a web page, an HTTP status, no
network, a full disk) is one line, with the cache byte for byte as it was."""

import fcntl
import hashlib
import json
import logging
import os
import threading
import time

import pytest

from nerfexp.data.archives import MEMBER_BYTES
from nerfexp.data.catalog import parse_entry
from nerfexp.data.scene_cache import (
    cache_lock,
    cached_folder,
    checksum_path,
    fetch_scene,
    scene_folder,
    scene_record_path,
    source_key,
)
from nerfexp.downloads import ATTEMPTS
from nerfexp.errors import DatasetError
from tests.data.archive_files import Item, declaring, folder_files, scene_items, tar_bytes, zip_bytes
from tests.data.archive_server import Served, local_only, no_network, refused_address, serving
from tests.helpers import digests, fill_disk, small_disk

PATH = "/scenes/chair.zip"  # where the lab's entry says its archive is, on its own host
ARCHIVE = zip_bytes(scene_items("chair"))
OTHER = zip_bytes(scene_items("table", seed=3))  # another scene, fetched first: the cache's earlier state


@pytest.fixture(autouse=True)
def local(monkeypatch) -> list:
    """No connection but to 127.0.0.1 (the servers these tests start)."""
    return local_only(monkeypatch)


def lab_entry(sha256: str | None = hashlib.sha256(ARCHIVE).hexdigest(), size: int | None = None,
              name: str = "mylab/chair", path: str = "chair", urls: tuple[str, ...] = (f"https://lab.example{PATH}",)):
    """A user's entry, read as a catalogue's is: its host is never reached (the tests' mirror stands for it)."""
    item = {"name": name, "format": "blender", "url": list(urls), "sha256": sha256, "path": path,
            **({} if size is None else {"size": size})}
    return parse_entry(item, "lab.yaml: entry 0", "lab.yaml")


def state(cache) -> dict[str, str]:
    """The cache's files and their digests: what a failure must leave as it found."""
    return digests(cache) if cache.exists() else {}


@pytest.fixture
def earlier(tmp_path):
    """A cache that holds another scene already, and a server for it."""
    cache = tmp_path / "cache"
    with serving({"/scenes/table.zip": Served(OTHER)}) as server:
        fetch_scene(lab_entry(hashlib.sha256(OTHER).hexdigest(), name="mylab/table", path="table",
                              urls=("https://lab.example/scenes/table.zip",)), server.address, cache)
    return cache


def test_a_scene_is_downloaded_verified_unpacked_and_recorded_then_found_offline(tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    entry = lab_entry()
    with serving({PATH: Served(ARCHIVE)}) as server:
        record = fetch_scene(entry, server.address, cache)
    digest = hashlib.sha256(ARCHIVE).hexdigest()
    assert record == {"name": "mylab/chair", "catalog": "lab.yaml", "url": f"https://lab.example{PATH}",
                      "downloaded_from": server.url(PATH), "path": "chair", "sha256": digest, "size": len(ARCHIVE),
                      "checksum": "pinned", "sha256_from": "given by its catalogue", "recorded": record["recorded"],
                      "unpacked": record["unpacked"], "folder": str(scene_folder(cache, "mylab/chair"))}
    assert server.requests == [(PATH, None)]
    expected = {i.name.removeprefix("chair/"): i.data for i in scene_items("chair")
                if i.name.startswith("chair/") and i.kind == "file"}
    assert folder_files(scene_folder(cache, "mylab/chair")) == expected  # the folder alone, README not
    assert (cache / "archives" / digest).read_bytes() == ARCHIVE
    assert json.loads(scene_record_path(cache, "mylab/chair").read_text()) == record
    assert list((cache / "downloads").iterdir()) == []
    tried = no_network(monkeypatch)
    assert fetch_scene(entry, "http://127.0.0.1:9", cache) == record and cached_folder(entry, cache).is_dir()
    assert tried == []  # offline: not one connection attempted


def pinned(data: bytes) -> tuple[dict, Served]:
    """An archive served as it is, its digest pinned by the entry: what fails lies in its members."""
    return {"sha256": hashlib.sha256(data).hexdigest()}, Served(data)


BOMB = declaring(zip_bytes([Item("chair/transforms_train.json", data=b"{}")]), 0xF000_0000)  # its index lies
FAILURES = {  # what goes wrong -> (the entry's changes, what the server serves, the line's words)
    "a changed byte": ({}, Served(ARCHIVE[:100] + bytes([ARCHIVE[100] ^ 1]) + ARCHIVE[101:]),
                       f"checksum mismatch: its SHA-256 is {{found}}, expected {hashlib.sha256(ARCHIVE).hexdigest()} "
                       "(pinned: given by its catalogue)"),
    "a wrong size": ({"size": len(ARCHIVE) + 1}, Served(ARCHIVE),
                     f"size mismatch: the server's file is {len(ARCHIVE):,} bytes, expected {len(ARCHIVE) + 1:,}"),
    "a climbing member": (*pinned(zip_bytes([*scene_items("chair"), Item("chair/../../evil.sh", data=b"x")])),
                          "member 'chair/../../evil.sh' would be written outside the folder it is unpacked into"),
    "an absolute member": (*pinned(zip_bytes([*scene_items("chair"), Item("/etc/evil", data=b"x")])),
                           "member '/etc/evil' would be written outside the folder"),
    "a symbolic link": (*pinned(zip_bytes([*scene_items("chair"), Item("chair/train/r_9.png", "symlink", b"/etc")])),
                        "member 'chair/train/r_9.png' is a link, not a file or a folder"),
    "a tar's hard link": (*pinned(tar_bytes([*scene_items("chair"), Item("chair/x.png", "hardlink", b"/etc/passwd")])),
                          "member 'chair/x.png' is a link, not a file or a folder"),
    "an oversized member": (*pinned(BOMB), f"declares {0xF000_0000:,} bytes, more than the {MEMBER_BYTES:,} nerfexp "
                                           "unpacks of one file"),
    "HTTP 404": ({}, Served(ARCHIVE, status=404), "HTTP 404 Not Found"),
    "HTTP 500": ({}, Served(ARCHIVE, status=500), "HTTP 500 Internal Server Error"),
    "a web page": ({}, Served(ARCHIVE, content_type="text/html; charset=utf-8"),
                   "the server sent a web page (text/html), not the file"),
    "a transfer that always breaks off": ({}, Served(ARCHIVE, cut_at=len(ARCHIVE) // 2, cuts=1000),
                                          f"the transfer broke off {ATTEMPTS} times in a row at byte "
                                          f"{len(ARCHIVE) // 2:,} (the connection broke off (IncompleteRead))"),
}


@pytest.mark.parametrize("changes, served, words", FAILURES.values(), ids=FAILURES)
def test_every_failure_is_one_line_and_leaves_the_cache_as_it_was(earlier, changes, served, words):
    before = state(earlier)
    with serving({PATH: served}) as server, pytest.raises(DatasetError) as failed:
        fetch_scene(lab_entry(**changes), server.address, earlier)
    line = str(failed.value)
    assert "\n" not in line and words.format(found=hashlib.sha256(served.data).hexdigest()) in line, line
    assert line.startswith("scene mylab/chair: ")  # the scene named, never a temporary file
    assert state(earlier) == before  # nothing of the fetch kept: no download, no folder, no record


def test_no_network_is_one_line_and_leaves_the_cache_as_it_was(earlier, monkeypatch):
    before = state(earlier)
    address = refused_address()
    with pytest.raises(DatasetError) as failed:
        fetch_scene(lab_entry(), address, earlier)
    assert str(failed.value) == (f"scene mylab/chair: {address}{PATH}: Connection refused: nothing of it kept in "
                                 f"{earlier}")
    no_network(monkeypatch)
    with pytest.raises(DatasetError, match=r": offline \(the test's no_network\): nothing of it kept"):
        fetch_scene(lab_entry(), "https://lab.example", earlier)
    assert state(earlier) == before


def test_a_transfer_that_breaks_off_continues_where_it_stopped(tmp_path):
    cut = len(ARCHIVE) // 3
    with serving({PATH: Served(ARCHIVE, cut_at=cut, cuts=2)}) as server:
        record = fetch_scene(lab_entry(), server.address, tmp_path / "cache")
    assert server.requests == [(PATH, None), (PATH, f"bytes={cut}-"), (PATH, f"bytes={cut}-")]
    assert record["sha256"] == hashlib.sha256(ARCHIVE).hexdigest()


def test_a_server_that_ignores_range_is_read_again_from_the_first_byte(tmp_path):
    cut = len(ARCHIVE) // 2
    with serving({PATH: Served(ARCHIVE, ranges=False, cut_at=cut, cuts=1)}) as server:
        record = fetch_scene(lab_entry(), server.address, tmp_path / "cache")
    assert server.requests == [(PATH, None), (PATH, f"bytes={cut}-"), (PATH, None)]  # a 200 to the range: restarted
    assert record["sha256"] == hashlib.sha256(ARCHIVE).hexdigest()


@pytest.mark.parametrize("left", [ARCHIVE[:1000], b"\0" * 1000], ids=["its start", "other bytes"])
def test_a_download_a_killed_process_left_is_continued_or_else_made_again(tmp_path, left):
    cache = tmp_path / "cache"
    entry = lab_entry()
    partial = cache / "downloads" / f"{source_key(entry)}.part"
    partial.parent.mkdir(parents=True)
    partial.write_bytes(left)
    with serving({PATH: Served(ARCHIVE)}) as server:
        record = fetch_scene(entry, server.address, cache)
    assert record["sha256"] == hashlib.sha256(ARCHIVE).hexdigest() and not partial.exists()
    again = [(PATH, None)] if left != ARCHIVE[:1000] else []  # bytes that were not its start: from the first byte
    assert server.requests == [(PATH, "bytes=1000-"), *again]


def test_a_full_disk_is_one_line_and_leaves_the_cache_as_it_was(tmp_path):
    with small_disk(tmp_path / "disk", "1m") as disk:
        cache = disk / "cache"
        with serving({"/scenes/table.zip": Served(OTHER), PATH: Served(ARCHIVE)}) as server:
            fetch_scene(lab_entry(hashlib.sha256(OTHER).hexdigest(), name="mylab/table", path="table",
                                  urls=("https://lab.example/scenes/table.zip",)), server.address, cache)
            before = state(cache)
            for leave in (len(ARCHIVE) // 2, len(ARCHIVE) + 4096):  # the download does not fit; then its unpacking
                fill_disk(disk / "filler", leave)
                with pytest.raises(DatasetError) as failed:
                    fetch_scene(lab_entry(), server.address, cache)
                assert str(failed.value).startswith(f"scene mylab/chair: no space left on the disk of {cache} (No "
                                                    "space left on device"), str(failed.value)
                assert str(failed.value).endswith("): the cache is as it was")
                assert state(cache) == before
                (disk / "filler").unlink()


def test_a_digest_recorded_on_first_download_is_what_every_later_download_must_match(tmp_path, caplog):
    cache = tmp_path / "cache"
    chair, table = lab_entry(sha256=None), lab_entry(sha256=None, name="mylab/table", path="chair/train")
    digest = hashlib.sha256(ARCHIVE).hexdigest()
    with serving({PATH: Served(ARCHIVE)}) as server, caplog.at_level(logging.INFO, "nerfexp"):
        record = fetch_scene(chair, server.address, cache)
    assert (record["checksum"], record["sha256"]) == ("recorded on first download", digest)
    recorded = json.loads(checksum_path(cache, chair).read_text())
    assert recorded == {"url": f"https://lab.example{PATH}", "sha256": digest, "size": len(ARCHIVE),
                        "recorded": record["recorded"]}
    assert f"this first download's, {digest}, is recorded in {checksum_path(cache, chair)}" in caplog.text
    (cache / "archives" / digest).unlink()  # archives removed to save space: the next scene downloads it again
    before = state(cache)
    changed = ARCHIVE[:-30] + bytes(30)
    with serving({PATH: Served(changed)}) as server, pytest.raises(DatasetError) as failed:
        fetch_scene(table, server.address, cache)
    assert (f"checksum mismatch: its SHA-256 is {hashlib.sha256(changed).hexdigest()}, expected {digest} (recorded on "
            f"first download on {record['recorded']} ({checksum_path(cache, chair)}))") in str(failed.value)
    assert state(cache) == before
    with serving({PATH: Served(ARCHIVE)}) as server:
        assert fetch_scene(table, server.address, cache)["sha256"] == digest  # the same bytes: unpacked


def test_a_damaged_record_of_a_digest_is_refused_never_taken_for_none(tmp_path):
    cache = tmp_path / "cache"
    entry = lab_entry(sha256=None)
    checksum_path(cache, entry).parent.mkdir(parents=True)
    checksum_path(cache, entry).write_text('{"sha256": "not a digest"}')
    with serving({PATH: Served(ARCHIVE)}) as server, pytest.raises(DatasetError) as failed:
        fetch_scene(entry, server.address, cache)
    assert str(failed.value).startswith(f"{checksum_path(cache, entry)}: not the digest nerfexp recorded for "
                                        f"https://lab.example{PATH}")
    assert server.requests == []


def test_the_next_address_is_tried_where_one_fails_and_a_changed_cached_archive_is_downloaded_again(tmp_path):
    cache = tmp_path / "cache"
    entry = lab_entry(urls=("https://a.example/gone.zip", f"https://b.example{PATH}"))
    with serving({PATH: Served(ARCHIVE)}) as server:
        assert fetch_scene(entry, server.address, cache)["downloaded_from"] == server.url(PATH)
        assert server.requests == [("/gone.zip", None), (PATH, None)]
        archive = cache / "archives" / hashlib.sha256(ARCHIVE).hexdigest()
        archive.write_bytes(ARCHIVE[:-1] + b"x")  # the cache's archive changed since
        table = lab_entry(name="mylab/table", path="chair/train", urls=entry.urls)
        assert fetch_scene(table, server.address, cache)["sha256"] == hashlib.sha256(ARCHIVE).hexdigest()
        assert archive.read_bytes() == ARCHIVE and len(server.requests) == 4  # downloaded again, whole


def test_a_scene_of_another_archive_than_the_entry_pins_is_fetched_again(tmp_path):
    cache = tmp_path / "cache"
    with serving({PATH: Served(OTHER), "/new.zip": Served(ARCHIVE)}) as server:
        old = fetch_scene(lab_entry(hashlib.sha256(OTHER).hexdigest(), path="table"), server.address, cache)
        new = fetch_scene(lab_entry(urls=("https://lab.example/new.zip",)), server.address, cache)
    assert old["sha256"] != new["sha256"] == hashlib.sha256(ARCHIVE).hexdigest()
    assert folder_files(scene_folder(cache, "mylab/chair"))["transforms_train.json"] == next(
        i.data for i in scene_items("chair") if i.name == "chair/transforms_train.json")


def test_fetches_into_one_cache_take_turns(tmp_path, caplog):
    cache = tmp_path / "cache"
    cache.mkdir()
    done = []
    with serving({PATH: Served(ARCHIVE)}) as server, caplog.at_level(logging.INFO, "nerfexp"):
        with cache_lock(cache):  # another process's fetch: a lock of the same folder, held
            worker = threading.Thread(target=lambda: done.append(fetch_scene(lab_entry(), server.address, cache)))
            worker.start()
            time.sleep(0.5)
            assert done == [] and server.requests == []  # waiting, nothing downloaded
        worker.join(timeout=60)
    assert done and f"waiting for another nerfexp process fetching into {cache}" in caplog.text
    fd = os.open(cache, os.O_RDONLY)
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # released: no lock file left, nothing held
    os.close(fd)
