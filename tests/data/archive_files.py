"""Archives the scene tests make: zip and tar files of given members (files, folders, links, devices), and tiny
Blender-format scenes packed in them."""

import functools
import io
import stat
import struct
import tarfile
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

from nerfexp.data.blender import write_blender
from tests.data.blender_views import ANGLE, make_views

KINDS = ("zip", "tar.gz")  # what a catalogue's archive may be (a plain, bzip2 or xz tar is read as tar.gz is)


@dataclass(frozen=True)
class Item:
    """A member to write: its ``name``, its ``kind`` (file, folder, symlink, hardlink, device) and its ``data`` (a
    link's target, as bytes)."""

    name: str
    kind: str = "file"
    data: bytes = b""


def zip_bytes(items: list[Item]) -> bytes:
    """A zip archive of ``items``, each name stored as given (``..`` and absolute ones included); a link as Info-ZIP
    stores one (its Unix mode in the external attributes, its target as its data)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for item in items:
            info = zipfile.ZipInfo(item.name + ("/" if item.kind == "folder" and not item.name.endswith("/") else ""))
            mode = {"file": stat.S_IFREG | 0o644, "folder": stat.S_IFDIR | 0o755, "symlink": stat.S_IFLNK | 0o777,
                    "hardlink": stat.S_IFLNK | 0o777, "device": stat.S_IFCHR | 0o644}[item.kind]
            info.external_attr = mode << 16
            archive.writestr(info, item.data)
    return buffer.getvalue()


def tar_bytes(items: list[Item]) -> bytes:
    """A gzip-compressed tar archive of ``items``, each name stored as given."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as archive:
        for item in items:
            info = tarfile.TarInfo(item.name)
            info.type = {"file": tarfile.REGTYPE, "folder": tarfile.DIRTYPE, "symlink": tarfile.SYMTYPE,
                         "hardlink": tarfile.LNKTYPE, "device": tarfile.CHRTYPE}[item.kind]
            if item.kind in ("symlink", "hardlink"):
                info.linkname = item.data.decode()
            info.size = len(item.data) if item.kind == "file" else 0
            archive.addfile(info, io.BytesIO(item.data) if item.kind == "file" else None)
    return buffer.getvalue()


def archive_bytes(kind: str, items: list[Item]) -> bytes:
    return zip_bytes(items) if kind == "zip" else tar_bytes(items)


def declaring(data: bytes, size: int) -> bytes:
    """The single-member zip ``data`` with its central directory declaring the member ``size`` bytes (a "zip bomb"'s
    index: readers that trust it write that much)."""
    at = data.index(b"PK\x01\x02")  # the central directory's entry; its uncompressed size at offset 24
    return data[:at + 24] + struct.pack("<I", size) + data[at + 28:]


def scene_items(prefix: str, seed: int = 0) -> list[Item]:
    """A tiny Blender-format scene (6 training, 2 validation and 2 test views of 16 x 12 pixels: SSIM's window fits)
    as the members of the folder ``prefix`` of an archive, after a file beside it (``README``), as a dataset's
    archive has."""
    return list(written_scene(prefix, seed))


@functools.cache
def written_scene(prefix: str, seed: int) -> tuple[Item, ...]:
    """``scene_items``, made once per test process."""
    items = [Item("README", data=b"not part of the scene")]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for split, n in (("train", 6), ("val", 2), ("test", 2)):
            write_blender(root, split, make_views(n=n, height=12, width=16, seed=seed + len(split)), ANGLE)
        items += folder_items(root, prefix)
    return tuple(items)


def folder_items(root: Path, prefix: str) -> list[Item]:
    """The files and folders under ``root`` as the members of the folder ``prefix`` of an archive."""
    return [Item(f"{prefix}/{path.relative_to(root).as_posix()}", "folder") if path.is_dir() else
            Item(f"{prefix}/{path.relative_to(root).as_posix()}", data=path.read_bytes())
            for path in sorted(root.rglob("*"))]


def folder_files(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` by its ``/``-separated path, with its bytes."""
    return {path.relative_to(folder).as_posix(): path.read_bytes() for path in sorted(folder.rglob("*"))
            if path.is_file()}
