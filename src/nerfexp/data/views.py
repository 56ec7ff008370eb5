"""A set of posed images: what every dataset format is loaded into, and when two of them are the same view.

A test score is a score on views training never saw: ``check_distinct_views`` refuses a training view among the
validation or test views, a near copy of one included (a camera that nearly coincides, an image that nearly
matches), and a view twice in one split, whatever the readers' spellings of its file. Validation views may be
test views (``holdout_split`` takes the first test views): validation only shows progress, and no score is
chosen by it.
"""

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from nerfexp.errors import DatasetError
from nerfexp.geometry.cameras import centre_spread
from nerfexp.geometry.lenses import Intrinsics, corner_pixels, pixel_rays
from nerfexp.reading import UnreadableFile, file_status, is_file

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")  # what a folder of photographs may hold
SPLIT_NAMES = {"train": "training", "val": "validation", "test": "test"}
MAY_SHARE = frozenset({"val", "test"})  # the splits that may hold one view: validation shows test views
# Two views are one view where their cameras nearly coincide and their images nearly match (check_distinct_views):
CENTRE_FRACTION = 0.01  # centres at most this fraction of the cameras' spread apart (centre_spread)
RAY_DEGREES = 0.5  # the rays through the images' centre and four corners at most this many degrees apart
IMAGE_PSNR_DB = 20.0  # the images, as scored, at least this PSNR to each other: an RMS difference of at most 0.1
PAIRS_PER_BLOCK = 1 << 22  # camera pairs compared at once (camera_matches): memory, not results
EXACT = "donot_use_mm_for_euclid_dist"  # torch.cdist's exact distances: 0 between equal points


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


def view_rays(views: Views) -> Tensor:
    """[N, 5, 3] float64: each view's unit world ray directions through its image's centre and its four corner
    pixels (``corner_pixels``), each through its own lens: where two views' rays agree at these five, they look
    the same way through every pixel (the rotation, roll included, the focal lengths, the principal point and the
    distortion all move them)."""
    H, W = views.height, views.width
    pixels = torch.cat([torch.tensor([[0.5 * W, 0.5 * H]], dtype=torch.float64), corner_pixels(H, W)])  # [5, 2]
    local = pixel_rays(pixels, views.intrinsics.to(torch.float64).unsqueeze(1))  # [N, 5, 3] in each camera
    return (views.c2w[:, None, :3, :3].double() @ local[..., None]).squeeze(-1)


def ray_degrees(a: Tensor, b: Tensor) -> Tensor:
    """[A, B]: the largest angle, in degrees, between rays ``a`` [A, 5, 3] and ``b`` [B, 5, 3] (``view_rays``) at
    the same pixel: 2 asin(|u - v| / 2) for unit u, v (exact at small angles, where acos(u . v) is not)."""
    chords = [torch.cdist(a[:, j], b[:, j], compute_mode=EXACT) for j in range(a.shape[1])]  # each [A, B]
    return torch.rad2deg(2 * torch.asin((torch.stack(chords).amax(0) / 2).clamp(max=1)))


def camera_matches(a: tuple[Tensor, Tensor], b: tuple[Tensor, Tensor], reach: float) -> list[tuple[int, int]]:
    """The pairs (i, k) of cameras i of ``a`` and k of ``b``, each (centres [N, 3], rays [N, 5, 3]: ``view_rays``),
    whose centres lie at most ``reach`` apart and whose rays at most ``RAY_DEGREES`` (``ray_degrees``). Compared
    ``PAIRS_PER_BLOCK`` pairs at a time: thousands of views against thousands without every pair in memory."""
    (a_centres, a_rays), (b_centres, b_rays) = a, b
    rows, pairs = max(1, PAIRS_PER_BLOCK // max(1, len(b_centres))), []
    for start in range(0, len(a_centres), rows):
        block = slice(start, start + rows)
        near = torch.cdist(a_centres[block], b_centres, compute_mode=EXACT) <= reach  # [rows, B]
        near &= ray_degrees(a_rays[block], b_rays) <= RAY_DEGREES
        pairs += [(start + i, k) for i, k in near.nonzero().tolist()]
    return pairs


def same_cameras(views: Views) -> list[tuple[int, int]]:
    """The pairs (i, k), k < i, of views of ``views`` whose poses and lenses are equal, value for value: found by
    grouping, in one pass over the views, however many there are."""
    groups: dict[tuple, list[int]] = {}
    lenses = views.intrinsics
    for i in range(len(views)):
        key = tuple(torch.cat([views.c2w[i].double().flatten(), lenses.params[i].double(),
                               lenses.distortion[i].double(), lenses.fisheye[i, None].double()]).tolist())
        groups.setdefault(key, []).append(i)
    return [(i, k) for group in groups.values() for place, i in enumerate(group) for k in group[:place]]


def image_psnr(a: Views, i: int, b: Views, k: int, background: Tensor) -> float:
    """The PSNR in dB of view ``i`` of ``a`` against view ``k`` of ``b`` (of one size), their images as they are
    scored (``Views.rgb_on`` the scene's ``background`` [3]), every pixel: -10 log10(mean squared difference);
    inf where they are equal."""
    scored = [views.subset(torch.tensor([n])).rgb_on(background).double() for views, n in ((a, i), (b, k))]
    mse = (scored[0] - scored[1]).square().mean().item()
    return math.inf if mse == 0 else -10 * math.log10(mse)


def likeness(fraction: float, degrees: float, psnr: float) -> str:
    """Why two views are one view, in words: their cameras ``fraction`` of the cameras' spread and ``degrees``
    apart, their images at ``psnr`` dB, against the tolerances."""
    if fraction == 0 and degrees == 0 and psnr == math.inf:
        return "they have the same pixels and the same pose"
    images = "identical" if psnr == math.inf else f"at {psnr:.1f} dB PSNR"
    return (f"their cameras {fraction:.2g} of the cameras' spread and {degrees:.2g} degrees apart, their images "
            f"{images}: one view is cameras within {CENTRE_FRACTION:g} of the spread and {RAY_DEGREES:g} degrees, "
            f"images at {IMAGE_PSNR_DB:g} dB or more")


def clash(splits: dict[str, Views], split: str, i: int, other: str, k: int, reason: str) -> DatasetError:
    """The DatasetError naming view ``i`` of ``split`` and view ``k`` of ``other``, one view for ``reason``, and the
    score it would spoil."""
    scored = split if other == "train" else other
    advice = ("a split holds each view once" if other == split else
              f"a score on views training saw is no {SPLIT_NAMES[scored]} score; keep it in one split")
    return DatasetError(f"the {SPLIT_NAMES[split]} view {splits[split].name(i)} and the {SPLIT_NAMES[other]} view "
                        f"{splits[other].name(k)} are one view ({reason}): {advice}")


def may_share(split: str, other: str) -> bool:
    """Whether a view of ``split`` may be one of ``other`` (``MAY_SHARE``: validation shows test views)."""
    return other != split and {other, split} <= MAY_SHARE


def check_distinct_files(splits: dict[str, Views]) -> None:
    """A DatasetError naming both views where two views that may not share (``may_share``) were read from one file
    (``file_identity``: any spelling, any link), whatever their poses and pixels."""
    seen: dict[tuple[int, int], list[tuple[str, int]]] = {}
    for split, views in splits.items():
        for i, source in enumerate(views.sources or ()):
            identity = source_identity(source)
            for other, k in seen.get(identity, []):
                if not may_share(split, other):
                    raise clash(splits, split, i, other, k, f"they name one file ({source.path})")
            if identity is not None:
                seen.setdefault(identity, []).append((split, i))


def check_distinct_views(splits: dict[str, Views], background: Tensor) -> dict:
    """A DatasetError naming both views where a training view is among the validation or test views, or a split
    holds one view twice: a test score must be a score on views training never saw, and a view counted twice
    weighs double. Validation and test views may be the same (``MAY_SHARE``).

    Two views are one view where they were read from one file (``check_distinct_files``), or where their cameras
    nearly coincide and their images nearly match: centres at most ``CENTRE_FRACTION`` of the spread of every
    view's camera centre (``centre_spread``) apart, the rays through their images' centre and corners at most
    ``RAY_DEGREES`` apart (``view_rays``; images of one size), and their images, as scored over ``background``
    [3], at least ``IMAGE_PSNR_DB`` to each other (``image_psnr``). Within a split only an exact copy is one view
    (the same pose and lens, ``same_cameras``, and the same pixels): a near copy there (a camera that paused in a
    video) only weighs its view a little more, and scores nothing training saw. Cameras are matched first, and
    images compared only for the pairs they match, earliest pair first. Returns what was checked, for the run's
    records: the tolerances, the spread, how many views, and how many image pairs the cameras left to compare."""
    check_distinct_files(splits)
    names = list(splits)
    cameras = {split: (views.c2w[:, :3, 3].double(), view_rays(views)) for split, views in splits.items()}
    centres = torch.cat([centre for centre, _ in cameras.values()])
    spread = centre_spread(centres) if len(centres) else 0.0
    pairs = []  # (split's place, i, other's place, k): view i of a split and view k of an earlier or the same split
    for place, split in enumerate(names):
        for other_place, other in enumerate(names[:place + 1]):
            if splits[split].rgba.shape[1:3] == splits[other].rgba.shape[1:3] and not may_share(split, other):
                matched = (same_cameras(splits[split]) if other == split else
                           camera_matches(cameras[split], cameras[other], CENTRE_FRACTION * spread))
                pairs += [(place, i, other_place, k) for i, k in matched]
    for place, i, other_place, k in sorted(pairs):
        split, other = names[place], names[other_place]
        psnr = image_psnr(splits[split], i, splits[other], k, background)
        if psnr >= (math.inf if other == split else IMAGE_PSNR_DB):
            distance = torch.linalg.vector_norm(cameras[split][0][i] - cameras[other][0][k]).item()
            degrees = ray_degrees(cameras[split][1][i:i + 1], cameras[other][1][k:k + 1]).item()
            raise clash(splits, split, i, other, k, likeness(distance / spread if distance else 0.0, degrees, psnr))
    return {"centre_fraction": CENTRE_FRACTION, "centre_spread": spread, "ray_degrees": RAY_DEGREES,
            "image_psnr_db": IMAGE_PSNR_DB, "views": len(centres), "image_pairs": len(pairs)}
