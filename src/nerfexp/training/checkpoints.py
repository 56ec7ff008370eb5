"""Checkpoints written whole: a checkpoint is replaced by a rename, never rewritten in place.

Lightning's ``TorchCheckpointIO`` saves through an fsspec transaction, which writes the file under
``TMPDIR`` and then moves it to the checkpoint's path. Where ``TMPDIR`` is another file system than the
run (a tmpfs ``/tmp``, a cluster node's scratch) that move is a copy over the previous checkpoint, and a
process killed during it (a time limit, the out-of-memory killer) leaves neither the old checkpoint nor
the new one to resume from. ``AtomicCheckpointIO`` streams ``torch.save`` into a temporary file in the
checkpoint's own folder and renames it over the checkpoint (``nerfexp.files.atomic_file``), so a kill
at any moment leaves the previous checkpoint whole. Every trainer config uses it (``trainer.plugins``).
"""

from pathlib import Path
from typing import Any

import torch
from fsspec.core import url_to_fs
from fsspec.implementations.local import LocalFileSystem
from lightning.pytorch.plugins.io import TorchCheckpointIO

from nerfexp.files import atomic_file


class AtomicCheckpointIO(TorchCheckpointIO):
    """``TorchCheckpointIO`` whose saves to a local path are atomic whatever ``TMPDIR`` is (see the
    module); loading and removing are Lightning's. A remote path (``s3://...``, whose uploads appear
    whole) or ``storage_options`` (which Lightning's refuses) go to Lightning's save."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path, storage_options: Any = None) -> None:
        filesystem, local_path = url_to_fs(str(path))  # a file:// address: its path
        if storage_options is not None or not isinstance(filesystem, LocalFileSystem):
            super().save_checkpoint(checkpoint, path, storage_options)
            return
        with atomic_file(Path(local_path)) as file:  # streamed: no second copy of the checkpoint in memory
            torch.save(checkpoint, file)
