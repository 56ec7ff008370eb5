"""One folder of a zip or tar archive unpacked, safely: every member of the archive is checked before anything is
written, and nerfexp writes the regular files and folders under the folder asked for itself, one by one (never
``extractall``), into a folder its caller made for them.

Refused, in one line naming the archive and the member, before anything is written:

- a name that leaves the folder it is unpacked into: absolute (``/etc/x``, ``C:/x``) or climbing (``..``), anywhere
  in the archive (a backslash counts as a separator, as an archive made on Windows means it);
- a symbolic or hard link, a device or a pipe, anywhere in the archive: a scene is images and the files that pose
  them, and a link is the classic way an archive writes outside its folder;
- a member larger than ``Limits.member_bytes``, members under the folder that total more than
  ``Limits.total_bytes``, or more than ``Limits.members`` of them (the sizes are those the archive declares, which
  is all a zip's reader yields: it stops at a member's declared size and checks its CRC-32, and a tar member is its
  declared size), and a total larger than the free space of the disk it goes to;
- one name written twice, or as a file and as a folder; a folder the archive does not hold.

A tar member is also passed through ``tarfile.data_filter`` (Python's own filter for archives from elsewhere) as
it is written. What fails while writing (a damaged member, its CRC-32, a full disk) is the caller's to clean up:
the folder it made is then incomplete.
"""

import errno
import os
import re
import shutil
import stat
import tarfile
import zipfile
import zlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import BinaryIO

from nerfexp.errors import DatasetError

MEMBER_BYTES = 1 << 31  # one file: 2 GiB, far above any image, camera file or sparse model of a scene
TOTAL_BYTES = 1 << 38  # one scene's folder: 256 GiB, above any scene a catalogue names (a big capture, every size)
MEMBERS = 1 << 20  # files and folders under one scene's folder
BLOCK = 1 << 20  # bytes copied at a time
DRIVE = re.compile(r"[A-Za-z]:")  # a Windows drive letter starting a name


@dataclass(frozen=True)
class Limits:
    """What one scene's folder may hold (the module's docstring)."""

    member_bytes: int = MEMBER_BYTES
    total_bytes: int = TOTAL_BYTES
    members: int = MEMBERS


@dataclass(frozen=True)
class Member:
    """A member of an archive as its index declares it: its ``name`` (``/``-separated, as stored), its ``kind``
    (``file``, ``folder``, ``link``, ``device`` or ``other``) and its ``size`` in bytes."""

    name: str
    kind: str
    size: int


def zip_kind(info: zipfile.ZipInfo) -> str:
    """A zip member's kind: a folder by its name, else from the Unix mode its external attributes carry (none,
    from an archiver that records none: a file)."""
    if info.is_dir():
        return "folder"
    mode = info.external_attr >> 16
    if not mode or stat.S_ISREG(mode):
        return "file"
    return "link" if stat.S_ISLNK(mode) else "device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "other"


def tar_kind(info: tarfile.TarInfo) -> str:
    if info.isreg():
        return "file"
    if info.isdir():
        return "folder"
    return "link" if info.issym() or info.islnk() else "device" if info.ischr() or info.isblk() else "other"


@contextmanager
def opened(archive: Path, label: str) -> Iterator[tuple[list[Member], Callable[[int], BinaryIO]]]:
    """The members of the zip or tar (plain, gzip, bzip2 or xz) ``archive``, in the order stored, and a function
    opening the member of a given index for reading; a DatasetError naming it (``label``) where it is neither, or
    damaged (also where the damage shows while a member is read inside the block)."""
    try:
        if zipfile.is_zipfile(archive):
            with zipfile.ZipFile(archive) as zipped:
                infos = zipped.infolist()
                yield [Member(i.filename, zip_kind(i), i.file_size) for i in infos], lambda k: zipped.open(infos[k])
        elif tarfile.is_tarfile(archive):
            with tarfile.open(archive, "r:*") as tarred:
                infos = tarred.getmembers()
                members = [Member(i.name, tar_kind(i), i.size) for i in infos]
                yield members, lambda k: tar_member(tarred, infos[k], label)
        else:
            raise DatasetError(f"{label}: not a zip or tar archive")
    except (zipfile.BadZipFile, zipfile.LargeZipFile, tarfile.TarError, EOFError, zlib.error, RuntimeError) as error:
        raise DatasetError(f"{label}: a damaged archive ({' '.join(str(error).split())})") from None


def tar_member(tarred: tarfile.TarFile, info: tarfile.TarInfo, label: str) -> BinaryIO:
    """A regular tar member's bytes, once ``tarfile.data_filter`` passes it (where this Python has it); a DatasetError
    naming the archive (``label``) and the member otherwise."""
    data_filter = getattr(tarfile, "data_filter", None)
    if data_filter is not None:
        try:
            data_filter(info, "/nonexistent/destination")  # names and kinds: the folder itself is never used
        except tarfile.FilterError as error:
            raise DatasetError(f"{label}: member {info.name!r} is refused by tarfile's data filter ({error})") from None
    return tarred.extractfile(info)


def name_parts(name: str) -> tuple[str, ...]:
    """A member's name as the folders and file it names, ``.`` and empty parts left out (a backslash counts as a
    separator)."""
    return tuple(part for part in PurePosixPath(name.replace("\\", "/")).parts if part not in (".", ""))


def escapes(name: str) -> bool:
    """Whether the member ``name`` would leave the folder it is unpacked into: absolute, on a drive, or ``..``."""
    text = name.replace("\\", "/")
    parts = text.split("/")
    return text.startswith("/") or bool(DRIVE.match(parts[0])) or ".." in parts


def selected(members: list[Member], inside: str, archive: str, limits: Limits) -> list[tuple[int, tuple[str, ...]]]:
    """The members under the folder ``inside`` of the archive named ``archive`` to write (their indices and names
    below ``inside``), once every member passes the module docstring's checks; a DatasetError naming the first that
    does not."""
    folder = name_parts(inside)
    chosen, total, files, folders = [], 0, set(), set()
    for index, member in enumerate(members):
        where = f"{archive}: member {member.name!r}"
        if escapes(member.name) or not name_parts(member.name):
            raise DatasetError(f"{where} would be written outside the folder it is unpacked into (an absolute name "
                               "or '..'): the archive is refused")
        if member.kind not in ("file", "folder"):
            raise DatasetError(f"{where} is a {'link' if member.kind == 'link' else member.kind + ' file'}, not a "
                               "file or a folder: the archive is refused (a scene is files in folders)")
        if member.size > limits.member_bytes:
            raise DatasetError(f"{where} declares {member.size:,} bytes, more than the {limits.member_bytes:,} "
                               "nerfexp unpacks of one file: the archive is refused")
        parts = name_parts(member.name)
        if parts[:len(folder)] != folder or len(parts) == len(folder):
            continue
        relative = parts[len(folder):]
        if relative in files or (member.kind == "file" and relative in folders):
            raise DatasetError(f"{where} names a file twice, or a file and a folder: the archive is refused")
        (files if member.kind == "file" else folders).add(relative)
        folders.update(relative[:n] for n in range(1, len(relative)))
        total += member.size
        chosen.append((index, relative))
        if total > limits.total_bytes or len(chosen) > limits.members:
            raise DatasetError(f"{archive}: the folder {inside!r} holds more than {limits.total_bytes:,} bytes or "
                               f"{limits.members:,} members, what nerfexp unpacks of one scene: the archive is "
                               "refused")
    if files & folders:
        clash = "/".join(sorted(files & folders)[0])
        raise DatasetError(f"{archive}: {clash!r} under {inside!r} is a file and a folder: the archive is refused")
    if not files:
        tops = sorted({name_parts(m.name)[0] for m in members if name_parts(m.name)})[:5]
        raise DatasetError(f"{archive} holds no file under the folder {inside!r} (its top folders: "
                           f"{', '.join(tops) or 'none'})")
    return chosen


def copy_member(source: BinaryIO, target: Path, size: int, where: str) -> None:
    """``size`` bytes of ``source`` into the new file ``target`` (never through a link, never over a file); a
    DatasetError naming ``where`` where the member holds more."""
    fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o644)
    written = 0
    with os.fdopen(fd, "wb") as file:
        for block in iter(lambda: source.read(BLOCK), b""):
            written += len(block)
            if written > size:
                raise DatasetError(f"{where} holds more than the {size:,} bytes it declares: the archive is refused")
            file.write(block)


def unpack_folder(archive: Path, inside: str, destination: Path, limits: Limits = Limits(),
                  label: str | None = None) -> int:
    """The files and folders under the folder ``inside`` of ``archive`` written into the existing, empty folder
    ``destination`` (``inside`` itself left out of the names), once every member passes the module docstring's
    checks; the bytes written. A DatasetError naming the archive (``label``, None: its path) and the member; an
    OSError of ENOSPC naming ``destination`` where the disk's free space is less than the folder's total."""
    label = str(archive) if label is None else label
    with opened(archive, label) as (members, member_file):
        chosen = selected(members, inside, label, limits)
        total = sum(members[index].size for index, _ in chosen)
        free = shutil.disk_usage(destination).free
        if total > free:
            raise OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)}: {total:,} bytes to unpack, {free:,} free",
                          str(destination))
        for index, relative in chosen:
            target = destination.joinpath(*relative)
            if members[index].kind == "folder":
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            with member_file(index) as source:
                copy_member(source, target, members[index].size, f"{label}: member {members[index].name!r}")
    return total
