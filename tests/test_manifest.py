"""The manifest: a file is nerfexp's while its size and SHA-256 equal its record; a damaged or huge manifest
proves nothing, in one line; two processes recording into one folder at once keep every record."""

import hashlib
import json
import multiprocessing
import os
import re

import pytest

from nerfexp import manifest
from nerfexp.errors import NerfexpError


def test_a_file_is_ours_while_it_matches_its_record(tmp_path):
    (tmp_path / "a.txt").write_text("ours")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "b.png").write_bytes(b"\x89PNG ours")
    manifest.record(tmp_path, ["a.txt", "sub/b.png", "never.txt"])
    records = json.loads((tmp_path / manifest.MANIFEST).read_text())["files"]
    assert records == {"a.txt": {"size": 4, "sha256": hashlib.sha256(b"ours").hexdigest()},
                       "sub/b.png": {"size": 9, "sha256": hashlib.sha256(b"\x89PNG ours").hexdigest()}}
    assert manifest.unproven(tmp_path, ["a.txt", "sub/b.png", "missing.txt"]) == []  # a missing file is fine

    (tmp_path / "a.txt").write_text("mine")  # the same size, other bytes: the hash tells
    (tmp_path / "sub" / "b.png").write_bytes(b"longer: a user's own picture")
    (tmp_path / "c.txt").write_text("never recorded")
    os.symlink(tmp_path / "c.txt", tmp_path / "link")  # a link is never a file nerfexp wrote
    assert manifest.unproven(tmp_path, ["a.txt", "sub/b.png", "c.txt", "link"]) == ["a.txt", "sub/b.png", "c.txt",
                                                                                   "link"]
    with pytest.raises(NerfexpError) as error:
        manifest.check_ours(tmp_path, ["a.txt"], "nerfexp-x", "move {it}, or choose another folder")
    assert str(error.value) == (f"{tmp_path / 'a.txt'} is not a file nerfexp-x wrote (it is not in "
                                f"{tmp_path / manifest.MANIFEST}, or changed since): move it, or choose another folder")
    with pytest.raises(NerfexpError, match=re.escape(f"{tmp_path / 'c.txt'}, {tmp_path / 'link'} are not files "
                                                     "nerfexp-x wrote (they are not in ")):
        manifest.check_ours(tmp_path, ["c.txt", "link", "missing.txt"], "nerfexp-x", "move {it}")

    (tmp_path / "a.txt").unlink()
    manifest.record(tmp_path, ["a.txt"])  # gone: its record goes too
    assert list(json.loads((tmp_path / manifest.MANIFEST).read_text())["files"]) == ["sub/b.png"]


def test_a_folder_replaced_as_a_whole_forgets_the_records_of_files_gone(tmp_path):
    for name in ("0000.png", "0001.png", "0002.png"):
        (tmp_path / "render" / "rgb").mkdir(parents=True, exist_ok=True)
        (tmp_path / "render" / "rgb" / name).write_bytes(name.encode())
    (tmp_path / "status.json").write_text("{}")
    manifest.record(tmp_path, ["status.json"])
    manifest.record_folder(tmp_path, "render")
    (tmp_path / "render" / "rgb" / "0002.png").unlink()
    manifest.record_folder(tmp_path, "render")
    assert list(json.loads((tmp_path / manifest.MANIFEST).read_text())["files"]) == [
        "render/rgb/0000.png", "render/rgb/0001.png", "status.json"]
    (tmp_path / "view").write_text("a file where a folder is expected")  # is itself the entry to check
    assert manifest.folder_files(tmp_path, "view") == ["view"] and manifest.unproven(tmp_path, ["view"]) == ["view"]


@pytest.mark.parametrize("content, reason", [
    (b"{not json", "not JSON"),
    (b'{"files": {"a.txt": {"size": 4, "sha256": "0"}}}', "not a nerfexp manifest"),
    (b'{"files": {"a.txt": {"size": 1e999, "sha256": "' + b"0" * 64 + b'"}}}', "not a nerfexp manifest"),
    (b"[" * 100_000 + b"]" * 100_000, "nested too deeply"),
    (b"\xff\xfe binary", "not UTF-8"),
    (None, "larger than"),  # a sparse file over MANIFEST_BYTES
    ("fifo", "not a regular file"),  # would block a read
])
def test_a_damaged_or_huge_manifest_proves_nothing_in_one_line_and_the_next_record_starts_afresh(tmp_path, content,
                                                                                                  reason):
    (tmp_path / "a.txt").write_text("ours")
    path = tmp_path / manifest.MANIFEST
    if content is None:
        with open(path, "wb") as file:
            file.truncate(manifest.MANIFEST_BYTES + 1)
    elif content == "fifo":
        os.mkfifo(path)
    else:
        path.write_bytes(content)
    with pytest.raises(NerfexpError) as error:
        manifest.check_ours(tmp_path, ["a.txt", "missing.txt"], "nerfexp-x", "move {it}")
    message = str(error.value)
    assert message.startswith(f"{path}: ") and reason in message and "\n" not in message, message
    assert message.endswith(f", so nothing shows {tmp_path / 'a.txt'} to be nerfexp-x's: move it")
    manifest.check_ours(tmp_path, ["missing.txt"], "nerfexp-x", "move {it}")  # nothing to replace: not read
    if content == "fifo":
        path.unlink()  # atomic_write renames over a file; a pipe there is someone's to remove
    manifest.record(tmp_path, ["a.txt"])
    assert manifest.unproven(tmp_path, ["a.txt"]) == []


def record_many(root, prefix: str, count: int) -> None:
    for i in range(count):
        name = f"{prefix}{i}.txt"
        (root / name).write_text(name)
        manifest.record(root, [name])


def test_two_processes_recording_into_one_folder_at_once_keep_every_record(tmp_path):
    context = multiprocessing.get_context("fork")
    writers = [context.Process(target=record_many, args=(tmp_path, prefix, 40)) for prefix in ("eval", "view")]
    for writer in writers:
        writer.start()
    for writer in writers:
        writer.join(60)
        assert writer.exitcode == 0
    records = json.loads((tmp_path / manifest.MANIFEST).read_text())["files"]
    assert sorted(records) == sorted(f"{prefix}{i}.txt" for prefix in ("eval", "view") for i in range(40))
    assert manifest.unproven(tmp_path, list(records)) == []
