"""A write that fails names what could not be written, never its temporary, and leaves what was there
whole (nerfexp.files: WriteError, atomic_file, atomic_directory, files staged to be replaced together). The
faults are real where the machine permits: a full tmpfs, a read-only bind mount (tests.helpers)."""

import errno
import os
import signal
from pathlib import Path

import pytest

from nerfexp.files import WriteError, atomic_directory, atomic_write, staged, written_name
from tests.helpers import digests, fill_disk, make_read_only, small_disk, unmount


def test_an_error_while_writing_is_named_by_what_was_written_never_by_its_temporary(tmp_path):
    path, folder = tmp_path / "run" / "eval.json", tmp_path / "run" / "export"
    cases = [
        (path, None, path),  # a write to a full disk names no file
        (path, path, path),
        (path, path.parent / ".eval.json.k2j9_x.tmp", path),  # atomic_file's temporary
        (path, tmp_path, path),  # a folder above it, made for it
        (path, path.parent / "metrics.jsonl", None),  # another file: read while writing, not this write
        (folder, folder.parent / ".export.a1b2.tmp" / "mesh.ply", folder / "mesh.ply"),  # the folder filled
        (folder, folder.parent / ".export.a1b2.old", folder),  # where the previous folder is moved aside
        (folder, folder / "points.ply", folder / "points.ply"),
        (folder, Path("/elsewhere/test/r_0.png"), None),
    ]
    for written, failed, expected in cases:
        error = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), *([] if failed is None else [str(failed)]))
        assert written_name(error, written) == expected, (written, failed)


def test_a_file_written_into_a_read_only_folder_is_a_write_error_naming_it_and_the_old_file_stays(tmp_path):
    folder = tmp_path / "checkpoints"
    folder.mkdir()
    path = folder / "last.ckpt"
    path.write_bytes(b"the previous checkpoint")
    make_read_only(folder)
    try:
        with pytest.raises(WriteError) as raised:
            atomic_write(path, b"the next one")
    finally:
        unmount(folder)
    assert (raised.value.filename, raised.value.errno) == (str(path), errno.EROFS)
    assert [p.name for p in folder.iterdir()] == ["last.ckpt"]  # no temporary left
    assert path.read_bytes() == b"the previous checkpoint"


def test_a_folder_written_to_a_full_disk_is_a_write_error_naming_it_and_the_old_folder_stays(tmp_path):
    with small_disk(tmp_path / "disk", "1m") as disk:
        out = disk / "export"
        out.mkdir()
        (out / "mesh.ply").write_bytes(b"the previous mesh")
        before = digests(out)
        fill_disk(disk / "filler")
        with pytest.raises(WriteError) as raised, atomic_directory(out, replace=True) as new:
            (new / "mesh.ply").write_bytes(bytes(1 << 16))  # a write names no file: the folder is named
        assert (raised.value.filename, raised.value.errno) == (str(out), errno.ENOSPC)
        assert digests(out) == before
        assert sorted(p.name for p in disk.iterdir()) == ["export", "filler"]  # nothing of the write left


def test_an_error_reading_another_file_while_writing_is_raised_as_it_is(tmp_path):
    with pytest.raises(FileNotFoundError) as raised, atomic_directory(tmp_path / "frames") as new:
        (new / "a.png").write_bytes((tmp_path / "video.mp4").read_bytes())
    assert not isinstance(raised.value, WriteError) and raised.value.filename == str(tmp_path / "video.mp4")
    assert list(tmp_path.iterdir()) == []


def test_a_signal_between_the_two_renames_of_a_replaced_folder_puts_the_previous_one_back(tmp_path, monkeypatch):
    out = tmp_path / "report_images"
    out.mkdir()
    (out / "view0.png").write_bytes(b"the previous picture")
    replace = os.replace

    def interrupted_after_the_first(source, target):
        replace(source, target)
        if Path(source) == out:  # the previous folder moved aside: Ctrl-C lands before the new one is moved in
            raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", interrupted_after_the_first)
    with pytest.raises(KeyboardInterrupt), atomic_directory(out, replace=True) as new:
        (new / "view0.png").write_bytes(b"the next picture")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report_images"]  # no .tmp or .old left
    assert [p.name for p in out.iterdir()] == ["view0.png"]
    assert (out / "view0.png").read_bytes() == b"the previous picture"


def staged_report(root: Path, fail: bool = False) -> None:
    """A page and its pictures' folder staged into ``root`` together (a report's shape); ``fail``: the block fails
    once both are written beside their places."""
    with staged(root) as staging:
        staging.file("page.html", b"the next page, naming view1.png")
        with staging.folder("pictures") as folder:
            (folder / "view1.png").write_bytes(b"the next picture")
        if fail:
            raise RuntimeError("stopped while it worked")


def previous_report(root: Path) -> dict[str, str]:
    (root / "pictures").mkdir(parents=True)
    (root / "pictures" / "view0.png").write_bytes(b"the previous picture")
    (root / "page.html").write_bytes(b"the previous page, naming view0.png")
    return digests(root)


def test_files_staged_together_replace_the_previous_ones_only_once_all_are_written(tmp_path):
    before = previous_report(tmp_path)
    with pytest.raises(RuntimeError):
        staged_report(tmp_path, fail=True)
    assert digests(tmp_path) == before  # the previous page and pictures, and no temporary
    staged_report(tmp_path)
    assert (tmp_path / "page.html").read_bytes() == b"the next page, naming view1.png"
    assert [p.name for p in (tmp_path / "pictures").iterdir()] == ["view1.png"]  # the folder replaced as a whole
    assert sorted(p.name for p in tmp_path.iterdir()) == ["page.html", "pictures"]


def test_a_signal_while_staged_files_move_into_place_takes_effect_once_all_are_there(tmp_path, monkeypatch):
    previous_report(tmp_path)
    replace, stops = os.replace, []

    def signalled_after_the_first(source, target):  # SIGINT as the page is moved in, before its pictures
        replace(source, target)
        if not stops:
            stops.append(Path(target).name)
            os.kill(os.getpid(), signal.SIGINT)

    def stop(signum, frame):
        raise RuntimeError("stopped by SIGINT")

    monkeypatch.setattr(os, "replace", signalled_after_the_first)
    before = signal.signal(signal.SIGINT, stop)
    try:
        with pytest.raises(RuntimeError, match="stopped by SIGINT"):
            staged_report(tmp_path)
        assert signal.getsignal(signal.SIGINT) is stop  # the handler from before the moves, back
    finally:
        signal.signal(signal.SIGINT, before)
    assert stops == ["page.html"]
    assert (tmp_path / "page.html").read_bytes() == b"the next page, naming view1.png"
    assert [p.name for p in (tmp_path / "pictures").iterdir()] == ["view1.png"]  # moved too, before the stop
    assert sorted(p.name for p in tmp_path.iterdir()) == ["page.html", "pictures"]
