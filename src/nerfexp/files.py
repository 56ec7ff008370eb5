"""Writing files and folders so that nothing a user made is ever half-written."""

import contextlib
import fnmatch
import os
import shutil
import signal
import tempfile
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import BinaryIO


def sync_folder(folder: Path) -> None:
    """Flush ``folder``'s entries to the disk, so that a rename into it outlasts a power cut; where the OS
    cannot open or flush a folder (Windows, some network file systems) nothing is done: the rename itself
    is already complete."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def sync_tree(folder: Path) -> None:
    """Flush every file under ``folder`` and every folder in it to the disk (links are left alone), so
    that once ``folder`` is renamed into place its contents outlast a power cut whole."""
    for parent, _, files in os.walk(folder):
        for name in files:
            file = os.path.join(parent, name)
            if not os.path.islink(file):
                fd = os.open(file, os.O_RDONLY)
                try:
                    os.fsync(fd)
                finally:
                    os.close(fd)
        sync_folder(Path(parent))


class WriteError(OSError):
    """An OSError met while writing a file or folder (a full disk, a read-only or immutable folder):
    ``filename`` names what could not be written as the user knows it, never the temporary file or folder
    beside it that a write fills first; ``strerror`` is the system's reason and ``errno`` its number."""


def written_name(error: OSError, path: Path) -> Path | None:
    """What ``error``, met while writing ``path``, failed to write: ``path`` where the error names no file
    (a ``write`` to a full disk), ``path``, a folder above it or a temporary beside it (``.NAME.*``); a file
    under ``path`` or its temporary folder (``.NAME.*.tmp``) by its name under ``path``. None where the
    error is about another file (one read while writing)."""
    if not isinstance(error.filename, str | bytes | os.PathLike):  # no file named, or a file descriptor
        return path
    failed = Path(os.fsdecode(error.filename))
    if failed.is_relative_to(path):  # it, or a file in it
        return failed
    if failed in path.parents:  # a folder made for it
        return path
    if not failed.is_relative_to(path.parent):
        return None
    first, *rest = failed.relative_to(path.parent).parts
    if not first.startswith(f".{path.name}."):
        return None
    return path.joinpath(*rest) if first.endswith(".tmp") else path


@contextlib.contextmanager
def writing(path: Path) -> Iterator[None]:
    """Inside the block, an OSError of writing ``path`` (``written_name``) is raised as a ``WriteError``
    naming what could not be written, from the original error; an OSError about another file as it is."""
    path = Path(path)
    try:
        yield
    except OSError as error:
        name = written_name(error, path)
        if name is None or (isinstance(error, WriteError) and Path(error.filename) == name):
            raise
        raise WriteError(error.errno, error.strerror or str(error), str(name)) from error


@contextlib.contextmanager
def temporary_file(path: Path) -> Iterator[tuple[BinaryIO, Path]]:
    """A new file beside ``path`` to fill, and its name: ``.NAME.*.tmp`` in ``path``'s folder (the same file system,
    whatever ``TMPDIR`` says: a rename across file systems is a copy, which a kill can cut short). Once the block
    succeeds it is flushed to the disk and readable by all, ready to be renamed over ``path``; if the block fails it
    is removed (it is this block's own: nothing else is touched)."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as file:
            yield file, Path(tmp)
            file.flush()
            os.fsync(file.fileno())
        os.chmod(tmp, 0o644)  # mkstemp's is 0o600
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def atomic_file(path: Path) -> Iterator[BinaryIO]:
    """A binary file to stream ``path``'s new contents into, so that a reader, or a process killed at any
    moment, finds the old file or the new one, never a part.

    The file is a temporary one beside ``path`` (``temporary_file``). Once the block succeeds it is flushed to the
    disk and renamed over ``path``; if the block fails it is removed (it is this block's own: nothing else is
    touched). An OSError of the write is a ``WriteError`` naming ``path``."""
    path = Path(path)
    with writing(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        with temporary_file(path) as (file, tmp):
            yield file
        try:
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
    sync_folder(path.parent)


def atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that a reader sees the old file or the new one, never a part
    (``atomic_file``)."""
    with atomic_file(path) as file:
        file.write(data)


@contextlib.contextmanager
def temporary_folder(path: Path) -> Iterator[Path]:
    """A new, empty folder beside ``path`` to fill (``.NAME.*.tmp``, never under ``TMPDIR``: see
    ``temporary_file``); once the block succeeds its contents are flushed to the disk (``sync_tree``), ready to be
    renamed to ``path`` (``move_folder``); if the block fails it is removed (it is this block's own)."""
    new = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"))
    try:
        os.chmod(new, 0o755)  # mkdtemp's is 0o700
        yield new
        sync_tree(new)
    except BaseException:
        shutil.rmtree(new, ignore_errors=True)
        raise


def move_folder(new: Path, path: Path, replace: bool) -> None:
    """The folder ``new`` renamed to ``path``. ``replace``: a previous ``path`` is moved aside and deleted after the
    new folder took its place, so a reader sees the old folder or the new one, never a part of one (for an instant
    between the two renames, none); an error or a signal between the renames puts the previous one back. Otherwise
    the rename fails where ``path`` is a folder that is not empty."""
    if not (replace and path.exists()):
        os.rename(new, path)
        return
    trash = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".old"))
    try:
        os.replace(path, trash / path.name)
        os.replace(new, path)
    except BaseException:  # an error or a signal between the renames: the previous folder back
        if not os.path.lexists(path) and os.path.lexists(trash / path.name):
            os.replace(trash / path.name, path)
        raise
    finally:
        shutil.rmtree(trash, ignore_errors=True)


@contextlib.contextmanager
def atomic_directory(path: Path, replace: bool = False) -> Iterator[Path]:
    """A new, empty folder beside ``path`` to fill (``temporary_folder``); once the block succeeds its contents are
    flushed to the disk and it is renamed to ``path`` (``move_folder``: with ``replace``, as a whole over a previous
    one), and if the block fails it is removed (it is this block's own: nothing else is touched). An OSError of the
    write is a ``WriteError`` naming ``path``, or the file under it that could not be written."""
    path = Path(path)
    with writing(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        with temporary_folder(path) as new:
            yield new
        try:
            move_folder(new, path, replace)
        except BaseException:
            shutil.rmtree(new, ignore_errors=True)
            raise
    sync_folder(path.parent)


STOPPING = (signal.SIGINT, signal.SIGTERM)  # the signals that stop a command (nerfexp.commands.signals)


@contextlib.contextmanager
def held_signals() -> Iterator[None]:
    """Inside the block SIGINT and SIGTERM wait: one received takes effect as the block ends, sent again to this
    process once the handler from before the block is back, so that what the block does (a few renames) is done
    whole. Outside the main thread, where Python sets no handler, nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    previous = {signum: signal.signal(signum, lambda signum, frame: held.append(signum)) for signum in STOPPING}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, signal.SIG_DFL if handler is None else handler)  # None: a handler set outside Python
        if held:
            signal.raise_signal(held[0])


class Staging:
    """New files and folders of the folder ``root``, each filled beside its place under a temporary name (``file``,
    ``folder``) and moved into place with the others (``staged``); ``files`` and ``folders`` name them
    (``/``-separated, relative to ``root``) in the order staged."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self.files: list[str] = []
        self.folders: list[str] = []
        self._moves: list[tuple[Path, str]] = []  # (a temporary, the entry it becomes), in the order staged

    def file(self, entry: str, data: bytes) -> None:
        """``data`` staged as the file ``entry``: written beside it (``temporary_file``). An OSError of the write
        is a ``WriteError`` naming ``root/entry``."""
        path = self.root / entry
        with writing(path):
            path.parent.mkdir(parents=True, exist_ok=True)
            with temporary_file(path) as (file, tmp):
                file.write(data)
        self._moves.append((tmp, entry))
        self.files.append(entry)

    @contextlib.contextmanager
    def folder(self, entry: str) -> Iterator[Path]:
        """A new, empty folder to fill, staged as the folder ``entry`` (``temporary_folder``), which it replaces as
        a whole. An OSError of the block's writes is a ``WriteError`` naming ``root/entry``, or its file."""
        path = self.root / entry
        with writing(path):
            path.parent.mkdir(parents=True, exist_ok=True)
            with temporary_folder(path) as new:
                yield new
        self._moves.append((new, entry))
        self.folders.append(entry)

    def move(self) -> None:
        """Each staged file and folder moved into place, in the order staged: a file renamed over its previous one,
        a folder replacing its previous one as a whole (``move_folder``)."""
        while self._moves:
            tmp, entry = self._moves[0]
            path = self.root / entry
            with writing(path):
                if tmp.is_dir():
                    move_folder(tmp, path, replace=True)
                else:
                    os.replace(tmp, path)
            self._moves.pop(0)
        sync_folder(self.root)

    def discard(self) -> None:
        """Every staged file and folder not moved into place removed (nothing else is touched)."""
        for tmp, _ in self._moves:
            if tmp.is_dir():
                shutil.rmtree(tmp, ignore_errors=True)
            else:
                tmp.unlink(missing_ok=True)
        self._moves.clear()


@contextlib.contextmanager
def staged(root: Path, moved: Callable[[Staging], None] = lambda staging: None) -> Iterator[Staging]:
    """A ``Staging`` of ``root`` to fill: once the block succeeds, every file and folder staged is moved into place
    (``Staging.move``) and then ``moved(staging)`` is called, with SIGINT and SIGTERM held until both are done
    (``held_signals``), so that a command stopped before leaves ``root`` as it was and one stopped while they move
    stops once all are in place: the files are replaced together or not at all. If the block fails, what it staged
    is removed and nothing else is touched."""
    staging = Staging(root)
    try:
        yield staging
        with held_signals():
            staging.move()
            moved(staging)
    finally:
        staging.discard()


def folder_entries(folder: Path) -> list[str]:
    """The files under ``folder`` (links and anything else that is not a folder included, links never
    followed), as sorted ``/``-separated paths relative to it; none where it does not exist. Empty folders
    are not entries: nothing in them can be overwritten. Where ``folder`` is a file, that file."""
    folder = Path(folder)
    if os.path.lexists(folder) and not folder.is_dir():
        return [folder.name]
    entries = []
    for parent, folders, files in os.walk(folder):
        links = [name for name in folders if os.path.islink(os.path.join(parent, name))]
        folders[:] = [name for name in folders if name not in links]
        relative = Path(parent).relative_to(folder)
        entries += [(relative / name).as_posix() for name in files + links]
    return sorted(entries)


def is_made(entry: str, made: tuple[str, ...]) -> bool:
    """Whether ``entry`` (a ``/``-separated relative path) is named by the ``fnmatch`` patterns ``made``: it,
    or a folder it lies in, matches one of them (``checkpoints`` names the whole folder). A name says what
    a file should be, never whose it is: that is the manifest's (``nerfexp.manifest``)."""
    parts = entry.split("/")
    prefixes = ["/".join(parts[:n]) for n in range(1, len(parts) + 1)]
    return any(fnmatch.fnmatchcase(prefix, pattern) for prefix in prefixes for pattern in made)


def foreign_message(folder: Path, foreign: list[str], maker: str, advice: str) -> str:
    """One line: ``FOLDER holds files MAKER did not make (the first three, ...): ADVICE``."""
    shown = ", ".join(foreign[:3]) + (", ..." if len(foreign) > 3 else "")
    return f"{folder} holds files {maker} did not make ({shown}): {advice}"
