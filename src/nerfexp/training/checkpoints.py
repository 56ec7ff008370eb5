"""Checkpoints written whole: a checkpoint is replaced by a rename, never rewritten in place.

Lightning's ``TorchCheckpointIO`` saves through an fsspec transaction, which writes the file under
``TMPDIR`` and then moves it to the checkpoint's path. Where ``TMPDIR`` is another file system than the
run (a tmpfs ``/tmp``, a cluster node's scratch) that move is a copy over the previous checkpoint, and a
process killed during it (a time limit, the out-of-memory killer) leaves neither the old checkpoint nor
the new one to resume from. ``AtomicCheckpointIO`` streams ``torch.save`` into a temporary file in the
checkpoint's own folder and renames it over the checkpoint (``nerfexp.files.atomic_file``), so a kill
at any moment leaves the previous checkpoint whole. Every trainer config uses it (``trainer.plugins``).

``torch.save`` turns the OSError of a write to a file object (a full disk) into a RuntimeError that names
neither the file nor the reason ("unexpected pos"); ``save_whole`` raises the OSError itself, which
``atomic_file`` makes a ``WriteError`` naming the checkpoint.
"""

from pathlib import Path
from typing import Any, BinaryIO

import torch
from fsspec.core import url_to_fs
from fsspec.implementations.local import LocalFileSystem
from lightning.pytorch.plugins.io import TorchCheckpointIO

from nerfexp.files import atomic_file


class ErrorKeepingWriter:
    """A binary file's ``write`` and ``flush``, keeping the OSError a write raised (``error``; None while
    none did), for a caller whose own error hides it (``torch.save``)."""

    def __init__(self, file: BinaryIO):
        self.file = file
        self.error: OSError | None = None

    def write(self, data) -> int:
        try:
            return self.file.write(data)
        except OSError as error:
            self.error = error
            raise

    def flush(self) -> None:
        try:
            self.file.flush()
        except OSError as error:
            self.error = error
            raise


def save_whole(obj: object, path: Path) -> None:
    """``torch.save(obj)`` to ``path`` atomically (``atomic_file``); a write that fails raises its own
    OSError (a ``WriteError`` naming ``path``), not torch's RuntimeError."""
    with atomic_file(path) as file:
        writer = ErrorKeepingWriter(file)
        try:
            torch.save(obj, writer)
        except RuntimeError:
            if writer.error is None:
                raise
            raise writer.error from None


class AtomicCheckpointIO(TorchCheckpointIO):
    """``TorchCheckpointIO`` whose saves to a local path are atomic whatever ``TMPDIR`` is (see the
    module); loading and removing are Lightning's. A remote path (``s3://...``, whose uploads appear
    whole) or ``storage_options`` (which Lightning's refuses) go to Lightning's save."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path, storage_options: Any = None) -> None:
        filesystem, local_path = url_to_fs(str(path))  # a file:// address: its path
        if storage_options is not None or not isinstance(filesystem, LocalFileSystem):
            super().save_checkpoint(checkpoint, path, storage_options)
            return
        save_whole(checkpoint, Path(local_path))  # streamed: no second copy of the checkpoint in memory
