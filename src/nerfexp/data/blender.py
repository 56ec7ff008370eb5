"""The NeRF "Realistic Synthetic 360" (Blender) dataset format.

A dataset root holds, per split, ``transforms_{split}.json``::

    {"camera_angle_x": <horizontal field of view, radians>,
     "frames": [{"file_path": "./train/r_0", "transform_matrix": <4x4 camera-to-world>}, ...]}

and the RGBA PNG images. ``file_path`` is relative to the root and usually has no extension
(``./train/r_0`` means ``train/r_0.png``). Matrices use the OpenGL convention of
``nerfexp.geometry.cameras``; images hold straight (not premultiplied) alpha.
"""

import json
import math
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import ClassVar

import torch
from torch import Tensor
from tqdm import tqdm

from nerfexp.data.base import FolderScene
from nerfexp.data.images import downscale_rgba, fit_factor, has_alpha, read_image
from nerfexp.data.views import Source, Views, check_shared_file
from nerfexp.domains import COUNT, Rule, breaks, is_real
from nerfexp.errors import DatasetError
from nerfexp.files import atomic_write
from nerfexp.geometry.cameras import POSE_LISTS, focal_from_fov, pose_problem
from nerfexp.geometry.lenses import Intrinsics
from nerfexp.pixels import png_bytes, to_uint8
from nerfexp.reading import UnreadableFile, name_problem, read_json

TRANSFORMS = "transforms_{split}.json"
BLENDER_HALF_SIDE = 1.5  # the synthetic scenes' objects lie in [-1.5, 1.5]^3
# an image file, by whether it has an alpha channel
ALPHA_KINDS = {True: "an RGBA image", False: "an RGB image (no alpha)"}
FIELD_OF_VIEW = ("a field of view in (0, pi) radians", lambda v: is_real(v) and 0 < v < math.pi)


def write_blender(root: Path, split: str, views: Views, camera_angle_x: float) -> None:
    """Write ``views`` as ``root/transforms_{split}.json`` and 8-bit PNGs ``root/{split}/r_{i}.png``."""
    root = Path(root)
    (root / split).mkdir(parents=True, exist_ok=True)
    frames = []
    for i, image in enumerate(to_uint8(views.rgba)):  # [H, W, 4] each
        atomic_write(root / split / f"r_{i}.png", png_bytes(image))
        frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": views.c2w[i].tolist()})
    text = json.dumps({"camera_angle_x": float(camera_angle_x), "frames": frames}, indent=2)
    atomic_write(root / TRANSFORMS.format(split=split), text.encode())


def pose_matrix(value, where: str) -> Tensor:
    """A 4x4 list of numbers (``POSE_LISTS``) that is a rigid camera pose (``pose_problem``) as a float64 tensor
    [4, 4], or a DatasetError naming ``where``."""
    if (wanted := breaks(POSE_LISTS, value)) is not None:
        raise DatasetError(f"{where}: 'transform_matrix' must be {wanted}, got {value!r:.80}")
    matrix = torch.tensor(value, dtype=torch.float64)
    if (problem := pose_problem(matrix)) is not None:
        raise DatasetError(f"{where}: 'transform_matrix' must be a rigid camera pose, but {problem}")
    return matrix


def checked_frames(path: Path, content: dict) -> list[tuple[str, dict]]:
    """The frames of the transforms file ``path`` (its JSON ``content``), each ``(where, frame)``: "PATH: frame
    i" and an object holding 'file_path' and 'transform_matrix'; a DatasetError naming the file (and the frame)
    where 'frames' is missing, not a non-empty list, or a frame lacks either key."""
    if "frames" not in content:
        raise DatasetError(f"{path}: missing key 'frames'")
    frames = content["frames"]
    if not isinstance(frames, list) or not frames:
        raise DatasetError(f"{path}: 'frames' must be a non-empty list, got {frames!r:.80}")
    for i, frame in enumerate(frames):
        where = f"{path}: frame {i}"
        if not isinstance(frame, dict):
            raise DatasetError(f"{where}: expected an object with 'file_path' and 'transform_matrix'")
        for key in ("file_path", "transform_matrix"):
            if key not in frame:
                raise DatasetError(f"{where}: missing key '{key}'")
    return [(f"{path}: frame {i}", frame) for i, frame in enumerate(frames)]


def read_transforms(path: Path) -> tuple[float, list[tuple[str, Tensor]]]:
    """``camera_angle_x`` and the frames ``(file_path, c2w [4, 4] float64)`` of a transforms file."""
    if not path.is_file():
        existing = ", ".join(sorted(p.name for p in path.parent.glob(TRANSFORMS.format(split="*")))) or "none"
        raise DatasetError(f"{path} does not exist; transforms files in {path.parent}: {existing}")
    try:
        content = read_json(path)  # bounded: a dataset from others
    except UnreadableFile as error:
        raise DatasetError(str(error)) from None
    if not isinstance(content, dict):
        raise DatasetError(f"{path}: expected a JSON object with keys 'camera_angle_x' and 'frames'")
    for key in ("camera_angle_x", "frames"):
        if key not in content:
            raise DatasetError(f"{path}: missing key '{key}'")
    angle = content["camera_angle_x"]
    if (wanted := breaks(FIELD_OF_VIEW, angle)) is not None:
        raise DatasetError(f"{path}: 'camera_angle_x' must be {wanted}, got {angle!r:.80}")
    parsed = []
    for where, frame in checked_frames(path, content):
        if not isinstance(frame["file_path"], str):
            raise DatasetError(f"{where}: 'file_path' must be a string, got {frame['file_path']!r:.80}")
        if (problem := name_problem(frame["file_path"])) is not None:
            raise DatasetError(f"{where}: 'file_path' {problem}, got {frame['file_path']!r:.80}")
        parsed.append((frame["file_path"], pose_matrix(frame["transform_matrix"], where)))
    return float(angle), parsed


def image_path(root: Path, file_path: str) -> Path:
    """The image a frame's ``file_path`` names: relative to ``root``, ``.png`` if it has no extension."""
    relative = file_path.removeprefix("./")
    path = root / relative
    return path if PurePosixPath(relative).suffix else path.with_name(path.name + ".png")


def load_blender(root, split: str, downscale: int = 1, max_views: int | None = None, stride: int = 1) -> Views:
    """Load one split of a Blender-format dataset as ``Views``.

    Keeps every ``stride``-th frame, then the first ``max_views`` of those; images are shrunk by
    the integer factor ``downscale`` (see ``downscale_rgba``) and the focal length is
    0.5 W / tan(0.5 camera_angle_x) for the final width W (fy follows the height where the factor shrank
    rows and columns differently). The images must agree in size and in having
    an alpha channel (``has_alpha``): an RGB image among RGBA ones would be read as opaque.
    """
    for name, value in (("downscale", downscale), ("stride", stride), ("max_views", max_views)):
        if value is not None and value < 1:
            raise DatasetError(f"{name} must be >= 1, got {value}")
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(
            f"data.root {root} does not exist: set the config key data.root to a folder holding "
            f"{TRANSFORMS.format(split=split)}"
        )
    transforms = root / TRANSFORMS.format(split=split)
    camera_angle_x, frames = read_transforms(transforms)
    numbers = range(len(frames))[::stride][:max_views]  # the frames kept, by their place in the file
    frames = frames[::stride][:max_views]
    sources = [Source(f"{transforms}: frame {k} ({file_path})", image_path(root, file_path))
               for k, (file_path, _) in zip(numbers, frames)]
    check_shared_file(sources)
    images, first = [], None
    for source, (file_path, _) in zip(sources, tqdm(frames, desc=f"loading {split}", unit="image", disable=None)):
        path = source.path
        image = read_image(path, f"file_path {file_path!r} in {transforms}")
        alpha = has_alpha(path)
        if first is None:
            first = (path, image.shape, alpha)
        elif image.shape != first[1]:
            (h, w), (h0, w0) = image.shape[:2], first[1][:2]
            raise DatasetError(f"{path}: image size {w}x{h} differs from {first[0]} ({w0}x{h0}); all images must match")
        elif alpha != first[2]:
            raise DatasetError(f"{path}: {ALPHA_KINDS[alpha]}, but {first[0]} is {ALPHA_KINDS[first[2]]}: a "
                               "scene's images must all have an alpha channel or none (one without is read as "
                               "opaque, its background learned as part of the scene)")
        images.append(image)
    rgba = torch.stack(images).float() / 255
    N, H, W, _ = rgba.shape  # views, rows, columns, channels
    if downscale > 1:
        rgba = downscale_rgba(rgba, downscale)
    h, w = rgba.shape[1:3]
    lenses = Intrinsics.pinhole(focal_from_fov(w, camera_angle_x), h, w, (N,))
    if h * W != H * w:  # rows and columns shrunk by different factors (the factor does not divide a side)
        lenses.params[:, 1] *= (h * W) / (H * w)  # fy follows the height
    c2w = torch.stack([matrix for _, matrix in frames]).float()
    return Views(rgba=rgba, c2w=c2w, intrinsics=lenses, sources=tuple(sources))


@dataclass(kw_only=True)
class BlenderScene(FolderScene):
    """A Blender-format dataset (``data=blender``): the training views, the first ``n_val``
    validation views, and every ``test_stride``-th test view, all shrunk by ``downscale`` and then,
    where ``max_side`` is set, by the smallest further integer factor that brings the longer image
    side to at most ``max_side`` pixels (so CPU-sized runs fit scenes of any resolution)."""

    DOMAINS: ClassVar[dict[str, Rule]] = {**FolderScene.DOMAINS, "downscale": COUNT, "test_stride": COUNT}

    downscale: int = 1
    test_stride: int = 1
    near: float = 2.0  # NeRF's bounds for its synthetic scenes
    far: float = 6.0

    def bounding_box(self) -> Tensor:
        """[2, 3]: [-1.5, 1.5]^3, the box that holds the objects of NeRF's synthetic scenes (as in nerfacc)."""
        return torch.tensor([[-BLENDER_HALF_SIDE] * 3, [BLENDER_HALF_SIDE] * 3])

    def views(self, split: str) -> Views:
        options = {"train": {"max_views": self.n_train}, "val": {"max_views": self.n_val},
                   "test": {"stride": self.test_stride}}[split]
        views = load_blender(self.folder(), split, self.downscale, **options)
        if split == "train" and self.n_train is not None and len(views.rgba) < self.n_train:
            raise DatasetError(f"data.n_train={self.n_train}: {self.folder() / TRANSFORMS.format(split=split)} "
                               f"has only {len(views.rgba)} views")
        factor = fit_factor(max(views.height, views.width), self.max_side)
        if factor == 1:
            return views
        return views.resized(downscale_rgba(views.rgba, factor))
