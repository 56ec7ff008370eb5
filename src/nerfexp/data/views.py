"""A set of posed images: what every dataset format is loaded into, and when two of them are the same view.

A test score is a score on views training never saw: ``check_distinct_views`` refuses a training view among the
validation or test views, and a view twice in one split, whatever the readers' spellings of its file. Validation
views may be test views (``holdout_split`` takes the first test views): validation only shows progress, and no
score is chosen by it.
"""

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from nerfexp.errors import DatasetError
from nerfexp.geometry.lenses import Intrinsics
from nerfexp.reading import UnreadableFile, file_status, is_file

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")  # what a folder of photographs may hold
SPLIT_NAMES = {"train": "training", "val": "validation", "test": "test"}
MAY_SHARE = frozenset({"val", "test"})  # the splits that may hold one view: validation shows test views


@dataclass(frozen=True)
class Source:
    """Where a view was read from: ``name``, how the dataset names it (its file, frame or row, for messages), and
    ``path``, the image file read."""

    name: str
    path: Path


@dataclass
class Views:
    """Posed RGBA images of one split.

    rgba: [N, H, W, 4] float32 in [0, 1], straight (not premultiplied) alpha.
    c2w: [N, 4, 4] float32 camera-to-world matrices, OpenGL convention (see ``nerfexp.geometry.cameras``).
    intrinsics: [N] each view's lens, float64: focal lengths, principal point and distortion in the images'
        pixels (``nerfexp.geometry.lenses``).
    mask: [N, H, W] bool, the pixels that count (in the loss and the scores), or None: all of them.
    sources: [N] each view's ``Source`` where the views were read from files, or None (rendered views).
    """

    rgba: Tensor
    c2w: Tensor
    intrinsics: Intrinsics
    mask: Tensor | None = None
    sources: tuple[Source, ...] | None = None

    @property
    def height(self) -> int:
        return self.rgba.shape[1]

    @property
    def width(self) -> int:
        return self.rgba.shape[2]

    def __len__(self) -> int:
        return self.rgba.shape[0]

    def subset(self, index: Tensor) -> "Views":
        """The views ``index`` [K] (indices or a mask), in that order."""
        kept = torch.arange(len(self))[index].tolist()  # [K] the views' places
        sources = None if self.sources is None else tuple(self.sources[i] for i in kept)
        return Views(rgba=self.rgba[index], c2w=self.c2w[index], intrinsics=self.intrinsics[index],
                     mask=None if self.mask is None else self.mask[index], sources=sources)

    def name(self, i: int) -> str:
        """How view ``i`` is named in messages: its source's name, or its place in the split."""
        return str(i) if self.sources is None else self.sources[i].name

    def resized(self, rgba: Tensor) -> "Views":
        """These views with their images replaced by ``rgba`` [N, H', W', 4], the same images resampled over
        the same extent (``downscale_rgba``): the lenses follow (``Intrinsics.resized``), and a pixel of the
        mask counts where every pixel under it counted (``shrink_mask``)."""
        size = tuple(rgba.shape[1:3])
        intrinsics = self.intrinsics.resized((self.height, self.width), size)
        return replace(self, rgba=rgba, intrinsics=intrinsics,
                       mask=None if self.mask is None else shrink_mask(self.mask, size))

    def rgb_on(self, background: Tensor) -> Tensor:
        """Colours composited over ``background`` [3]: [N, H, W, 3]."""
        rgb, alpha = self.rgba[..., :3], self.rgba[..., 3:]
        return rgb * alpha + background * (1 - alpha)


def shrink_mask(mask: Tensor, size: tuple[int, int]) -> Tensor:
    """Masks [N, H, W] bool shrunk to ``size`` (H', W') over the same extent by adaptive average pooling, as
    images are (``nerfexp.data.images.downscale_rgba``): a pixel counts where every pixel under it counted
    (a mean of ones is exactly 1)."""
    pooled = F.adaptive_avg_pool2d(mask[:, None].float(), size)[:, 0]  # [N, H', W']
    return pooled == 1


def holdout_split(n: int, holdout: int, n_val: int, n_train: int | None = None) -> dict[str, Tensor]:
    """Image indices per split of ``n`` images: test every ``holdout``-th (i % holdout == 0, the LLFF
    convention), train the first ``n_train`` of the rest (None: all; more than there are is a DatasetError),
    val the first ``n_val`` test ones (all of them where there are fewer)."""
    index = torch.arange(n)
    train, test = index[index % holdout != 0], index[index % holdout == 0]
    if n_train is not None and n_train > len(train):  # a cut would leave fewer views than the run records
        raise DatasetError(f"data.n_train={n_train}: only {len(train)} of the {n} images are training images "
                           f"(every {holdout}th is held out for testing)")
    return {"train": train[:n_train], "val": test[:n_val], "test": test}


def file_identity(path: Path) -> tuple[int, int] | None:
    """The file ``path`` resolves to, as (device, inode): one for every spelling of it (``a//b``, ``a/./b``), every
    symbolic link to it and every hard link; None where nothing is there (missing: its reader says so); an
    ``UnreadableFile`` where it cannot be looked up (``nerfexp.reading.file_status``: a NUL byte, a name too long)."""
    status = file_status(path)
    return None if status is None else (status.st_dev, status.st_ino)


def source_identity(source: Source) -> tuple[int, int] | None:
    """``file_identity`` of ``source``'s file; a DatasetError naming the file and the view where it cannot be looked
    up."""
    try:
        return file_identity(source.path)
    except UnreadableFile as error:
        raise DatasetError(f"{error} (named by {source.name})") from None


def is_named_file(path: Path, named_by: str) -> bool:
    """Whether ``path``, a file that ``named_by`` names (a frame's key, a row), is a regular file
    (``nerfexp.reading.is_file``); a DatasetError naming both where it cannot be looked up (a NUL byte, a name too
    long), never a traceback."""
    try:
        return is_file(path)
    except UnreadableFile as error:
        raise DatasetError(f"{error} (named by {named_by})") from None


def check_shared_file(sources: Sequence[Source]) -> None:
    """A DatasetError naming both where two of ``sources`` (of one split, or of every view a file lists) resolve
    to one file (``file_identity``): that image would count as two views. Looks at the files' names and links
    only, so a reader calls it before it reads any image."""
    seen: dict[tuple[int, int], Source] = {}
    for source in sources:
        identity = source_identity(source)
        if identity in seen:
            raise DatasetError(f"{seen[identity].name} and {source.name} name one file ({seen[identity].path}): "
                               "one view counted twice; list each image once")
        if identity is not None:
            seen[identity] = source


def same_view(a: Views, i: int, b: Views, j: int) -> str | None:
    """Why view ``i`` of ``a`` and view ``j`` of ``b`` are the same view, or None where they are not: their sources
    resolve to one file (``file_identity``), or their pixels and their poses are equal."""
    if a.sources is not None and b.sources is not None:
        identity = file_identity(a.sources[i].path)
        if identity is not None and identity == file_identity(b.sources[j].path):
            return f"they name one file ({b.sources[j].path})"
    if torch.equal(a.c2w[i], b.c2w[j]) and torch.equal(a.rgba[i], b.rgba[j]):
        return "they have the same pixels and the same pose"
    return None


def view_keys(views: Views, i: int) -> list[tuple]:
    """The keys under which view ``i`` may meet the same view elsewhere (``same_view``): its file's identity,
    where it was read from one, and its pose (equal pixels need an equal pose)."""
    keys = [("pose", *views.c2w[i].flatten().tolist())]
    if views.sources is not None and (identity := file_identity(views.sources[i].path)) is not None:
        keys.append(("file", *identity))
    return keys


def check_distinct_views(splits: dict[str, Views]) -> None:
    """A DatasetError naming both views where a training view is among the validation or test views, or a split
    holds one view twice (``same_view``: one file under any spelling or link, or the same pixels and pose): a test
    score must be a score on views training never saw, and a view counted twice weighs double. Validation and
    test views may be the same (``MAY_SHARE``). Views are grouped by ``view_keys``, so pixels are compared only
    between views of one pose."""
    met: dict[tuple, list[tuple[str, int]]] = {}
    for split, views in splits.items():
        for i in range(len(views)):
            keys = view_keys(views, i)
            candidates = dict.fromkeys(entry for key in keys for entry in met.get(key, []))
            for other, k in candidates:
                if other != split and {other, split} <= MAY_SHARE:
                    continue
                if (reason := same_view(splits[other], k, views, i)) is not None:
                    scored = split if other == "train" else other
                    advice = ("a split holds each view once" if other == split else
                              f"a score on views training saw is no {SPLIT_NAMES[scored]} score; keep it in one split")
                    raise DatasetError(f"the {SPLIT_NAMES[split]} view {views.name(i)} and the {SPLIT_NAMES[other]} "
                                       f"view {splits[other].name(k)} are one view ({reason}): {advice}")
            for key in keys:
                met.setdefault(key, []).append((split, i))
