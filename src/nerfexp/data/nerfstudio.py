"""nerfstudio's data format (``transforms.json``), as ``ns-process-data`` writes it from photographs, video,
Polycam, Record3D, Metashape or ODM, and Instant-NGP's variant of it (``colmap2nerf.py``).

The file's format, and how it is parsed and checked: ``nerfexp.data.transforms_file``.

Reading (``NerfstudioScene``):
- frames in ``file_path`` order (as nerfstudio orders them); ``file_path`` and ``mask_path`` relative to the
  root (no absolute path, no ``..``): a frame's files lie in the scene's folder;
- images: with ``downscale`` d > 1 from ``images_{d}/<file name>`` (``masks_{d}/`` for masks) where that
  folder exists, as ``ns-process-data`` writes them, else the full images shrunk by d on reading; then
  shrunk further to ``max_side``; the lenses follow the images' size (``Intrinsics.resized``);
- masks: 8-bit images, 0 where a pixel does not count (in neither the loss nor the scores);
- splits: the file's ``train_filenames`` / ``val_filenames`` / ``test_filenames`` where it lists them
  (``val`` the first ``n_val`` test views where it lists none), else every ``holdout``-th frame a test view
  (``holdout_split``, as for LLFF and COLMAP scenes); which rule made the split is ``split_rule()``; the lists'
  entries are matched to frames by ``spelling`` (``images//a.png`` is ``images/a.png``), a frame listed twice or
  in ``train_filenames`` and another list is refused (validation may list test frames), and so are two frames
  whose images are one file under any spelling or link (``check_shared_file``), before any image is read;
- every frame a file lists is read: frames whose image files do not exist are refused in one line, all of them
  counted, before any image of any split is read (``check_images_exist``; Instant-NGP's own loader drops them where
  its frames carry ``sharpness``, and its fox lists 67 frames for 50 images), or, with ``missing_images`` skip, left
  out of the scene (and of the file's split lists) with one line (``with_images``), ``frames_left_out()`` naming
  them for results.json;
- poses: camera centres moved and scaled to lie within ``bound`` of the origin (``normalize_centres``, as
  for COLMAP scenes);
- ray bounds: ``near`` and ``far`` where given, else from what the capture holds, the first that bounds the
  views of every frame (``found_bounds``; ``bounds_rule()`` says which, results.json records it as ``bounds``):
  1. sparse points: the PLY that ``ply_file_path`` names (nerfstudio's ``sparse_pc.ply``: COLMAP's points in the
     poses' coordinates), else a COLMAP model in the folder (``colmap/sparse/0``, ``sparse/0``, ``sparse``: its
     cameras matched to the frames by file name, its distances scaled by the cameras' spread); near and far as
     for COLMAP scenes (``nerfexp.data.sparse_points.near_far``), the points a camera sees being those in its
     view (a PLY records no visibility) or those COLMAP observed;
  2. Instant-NGP's scene box (``ngp_box``): the nearest and the farthest point of the box in any camera's view
     (``nerfexp.geometry.frusta.box_reach``: exact for the pyramid of the pixel rays);
  3. ``NEAR_FRACTION`` x ``bound`` and ``FAR_FACTOR`` x ``bound`` (every camera lies within ``bound``, so a ray
     crosses the cameras' ball within 2 ``bound``).
  near is at least ``NEAR_FRACTION`` x ``bound`` (a camera inside the box, or a stray point beside a camera, would
  give 0); every frame's camera counts, not only the training ones, since one near and far serve every render.

Every malformed field is a DatasetError naming the file, the frame and the key, before any image is read.
"""

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path, PurePosixPath
from typing import ClassVar

import torch
from torch import Tensor
from tqdm import tqdm

from nerfexp.data.base import FolderScene
from nerfexp.data.images import downscale_rgba, fit_factor, image_size, read_image
from nerfexp.data.sparse_points import near_far, read_ply_points
from nerfexp.data.transforms_file import (
    TRANSFORMS,
    Capture,
    Frame,
    downscaled_file,
    frame_lens_fields,
    read_capture,
    scene_file,
)
from nerfexp.data.views import Source, Views, check_shared_file, holdout_split, is_named_file, shrink_mask
from nerfexp.domains import COUNT, FAR, INTEGER_LIMIT, TEXT, Rule, choice, whole
from nerfexp.errors import DatasetError
from nerfexp.geometry.boxes import box_problem
from nerfexp.geometry.cameras import centre_spread, normalize_centres
from nerfexp.geometry.frusta import box_reach, in_view, view_planes
from nerfexp.geometry.lens_records import read_lens_record
from nerfexp.geometry.lenses import Intrinsics, inversion_problem

NEAR_FRACTION = 0.05  # near = 0.05 bound where not given
FAR_FACTOR = 2.0  # far = 2 bound where not given
MISSING_IMAGES = ("refuse", "skip")  # data.missing_images: frames whose images do not exist refused, or left out

log = logging.getLogger(__name__)


def colmap_point_bounds(model: Path, frames: list[Frame], c2w: Tensor) -> tuple[float, float] | None:
    """(near, far) from the sparse points of the COLMAP model in ``model`` for the ``frames`` posed by ``c2w``
    [N, 4, 4] (normalized), or None where fewer than two of its images match a frame by file name or none
    observes a point. The model's coordinates are its own (before nerfstudio's ``applied_transform``, any
    scale or re-centring): distances are measured there, from the matched images' camera centres to the
    points each observes (``near_far``), and scaled by the ratio of the cameras' spreads (the root mean square
    distance from their mean centre) in the frames' and in the model's coordinates, which a similarity keeps."""
    from nerfexp.data.colmap import cam_from_world, colmap_to_c2w, model_points  # they import pycolmap
    from nerfexp.data.colmap_sfm import read_model

    reconstruction = read_model(model)
    by_name = {PurePosixPath(reconstruction.images[i].name).name: i for i in reconstruction.reg_image_ids()}
    matched = [(k, by_name[name]) for k, frame in enumerate(frames)
               if (name := PurePosixPath(frame.file_path).name) in by_name]
    if len(matched) < 2:
        return None
    ids = [i for _, i in matched]
    centres = colmap_to_c2w(cam_from_world(reconstruction, ids))[:, :3, 3]
    ours = c2w[[k for k, _ in matched], :3, 3]
    spread = [centre_spread(c) for c in (ours, centres)]
    if not spread[1] > 0:
        return None
    points, observed = model_points(reconstruction, ids)
    bounds = near_far(centres, points, observed)
    ratio = spread[0] / spread[1]
    return None if bounds is None else (bounds[0] * ratio, bounds[1] * ratio)


def read_mask(path: Path, source: str) -> Tensor:
    """A mask image as bool [H, W]: True where the pixel counts (nonzero), as nerfstudio reads masks."""
    return read_image(path, source)[..., 0] > 0


@dataclass(frozen=True)
class PosedCapture:
    """A parsed transforms file with its poses normalized: the ``capture``, every frame's pose ``c2w``
    [N, 4, 4] float64 with the camera centres moved and scaled to lie within ``bound`` of the origin, and the
    ``centre`` [3] and ``scale`` that did it (a point p of the file is (p - centre) scale), and the frames left out
    for their missing images (``with_images``: their ``file_path``s)."""

    capture: Capture
    c2w: Tensor
    centre: Tensor
    scale: float
    left_out: tuple[str, ...] = ()


def with_images(capture: Capture, root: Path, downscale: int, missing: str) -> tuple[Capture, tuple[str, ...]]:
    """``capture`` as parsed, and no frame left out, where ``missing`` is refuse (``check_images_exist`` refuses its
    frames without an image when they are read); with skip, ``capture`` without the frames whose image file at
    ``downscale`` does not exist (``image_file``), in its frames and its split lists, said in one line, and their
    ``file_path``s in the file's order. A DatasetError where no frame's image exists."""
    if missing == "refuse":
        return capture, ()
    absent = [frame for frame in capture.frames
              if not is_named_file(image_file(root, frame, downscale)[0], f"{frame.where}'s file_path")]
    if not absent:
        return capture, ()
    if len(absent) == len(capture.frames):
        raise DatasetError(f"{capture.path}: none of the images of its {len(absent)} frames exists (the first: "
                           f"{image_file(root, absent[0], downscale)[0]})")
    names = {frame.file_path for frame in absent}
    splits = None if capture.splits is None else {
        split: [name for name in listed if name not in names] for split, listed in capture.splits.items()}
    log.warning("%s: the images of %d of its %d frames do not exist (the first: %s): those frames are left out "
                "(data.missing_images=skip; results.json's frames_left_out lists them)", capture.path, len(absent),
                len(capture.frames), absent[0].file_path)
    kept = [frame for frame in capture.frames if frame.file_path not in names]
    return replace(capture, frames=kept, splits=splits), tuple(frame.file_path for frame in absent)


def posed_capture(root: Path, transforms: str, downscale: int, bound: float, missing: str = "refuse") -> PosedCapture:
    """The transforms file ``transforms`` in ``root`` parsed (``read_capture``), its frames without an image left
    out where ``missing`` is skip (``with_images``), its frames' image files checked distinct
    (``check_shared_file``) and its poses normalized (``normalize_centres``); a DatasetError where the file does not
    exist, or the scene box, normalized, is not one an occupancy grid covers (``box_problem``)."""
    path = root / transforms
    if not path.is_file():
        raise DatasetError(f"{path} does not exist: data.root must be a folder holding {transforms} "
                           f"(nerfstudio's format; data.transforms names another file in it)")
    capture, left_out = with_images(read_capture(path), root, downscale, missing)
    check_shared_file([Source(frame.where, image_file(root, frame, downscale)[0]) for frame in capture.frames])
    c2w = torch.stack([frame.c2w for frame in capture.frames])
    normalized, _, centre, scale = normalize_centres(c2w, torch.zeros(0, 3, dtype=c2w.dtype), bound)
    box = None if capture.box is None else (capture.box - centre) * scale  # as bounding_box gives it
    if box is not None and (problem := box_problem(box)) is not None:
        raise DatasetError(f"{path}: the scene box of 'aabb_scale', 'scale' and 'offset', moved and scaled "
                           f"as the poses are (data.bound={bound}), {box.tolist()}, {problem}")
    return PosedCapture(capture, normalized, centre, scale, left_out)


def check_images_exist(images: list[Source]) -> None:
    """A DatasetError naming the first of the frames' image files (``images``) that does not exist, and how many
    more do not, where any does not: one line for all of them, before any image is read."""
    missing = [image for image in images if not is_named_file(image.path, f"{image.name}'s file_path")]
    if missing:
        more = (f", nor do the images of {len(missing) - 1} more of the file's {len(images)} frames" if missing[1:]
                else "")
        raise DatasetError(f"image {missing[0].path} does not exist (named by {missing[0].name}'s file_path){more}: "
                           "nerfexp reads every frame the file lists (Instant-NGP's loader skips such frames); "
                           "remove them from the file, bring their images, or leave them out with "
                           "data.missing_images=skip")


def image_file(root: Path, frame: Frame, downscale: int) -> tuple[Path, int, int]:
    """(path, shrink, stored): the image file to read for ``frame`` at ``downscale`` (``downscaled_file``), the
    factor still to shrink it by, and the factor it is stored smaller than its recorded ``w, h`` by (a folder's
    ``images_{d}`` are stored d times smaller)."""
    path, shrink = downscaled_file(root, frame.file_path, "images", downscale, f"{frame.where}'s file_path")
    return path, shrink, (downscale if shrink == 1 else 1)


@dataclass(frozen=True)
class FrameImage:
    """One frame read at the scene's downscale: ``rgba`` [1, H, W, 4] in [0, 1], ``mask`` [1, H, W] bool (True
    where a pixel counts) or None, the ``lens`` at that size, and its ``source`` (the frame and its file)."""

    rgba: Tensor
    mask: Tensor | None
    lens: Intrinsics
    source: Source


def frame_lens(frame: Frame, defaults: dict, path: Path, size: tuple[int, int], stored: int
               ) -> tuple[Intrinsics, tuple[int, int]]:
    """(lens, recorded): the lens of ``frame`` (its keys over the file's ``defaults``, ``frame_lens_fields``) at
    its recorded size (h, w), for the image ``path`` of ``size`` (h, w) stored ``stored`` times smaller; a
    DatasetError where the image's size, times ``stored``, is not the recorded one (within ``stored``)."""
    height, width = size
    fields = frame_lens_fields(frame, defaults, (height * stored, width * stored))
    recorded = (int(fields["h"]), int(fields["w"]))
    if abs(height * stored - recorded[0]) >= stored or abs(width * stored - recorded[1]) >= stored:
        raise DatasetError(f"{path}: image size {width}x{height} does not match {frame.where}'s w x h "
                           f"{recorded[1]}x{recorded[0]}" + (f" shrunk by {stored}" if stored > 1 else ""))
    return read_lens_record(fields), recorded


def check_invertible(lens: Intrinsics, size: tuple[int, int], where: str, checked: set) -> None:
    """A DatasetError naming ``where`` where ``lens`` cannot be inverted over an image of ``size`` (h, w)
    (``inversion_problem``); ``checked`` holds the lenses (with their sizes) found invertible, and gains this
    one: most captures share one lens, checked once."""
    key = (*lens.params.tolist(), *lens.distortion.tolist(), bool(lens.fisheye), *size)
    if key not in checked:
        if problem := inversion_problem(lens, *size):
            raise DatasetError(f"{where}: {problem}")
        checked.add(key)


def frame_mask(root: Path, frame: Frame, downscale: int) -> Tensor | None:
    """[1, H, W] bool: the mask of ``frame`` at ``downscale`` (``masks_{d}/`` where it exists, else the full mask
    shrunk), or None where the frame has none."""
    if frame.mask_path is None:
        return None
    path, shrink = downscaled_file(root, frame.mask_path, "masks", downscale, f"{frame.where}'s mask_path")
    mask = read_mask(path, f"{frame.where}'s mask_path")[None]  # [1, H, W]
    return mask if shrink == 1 else shrink_mask(mask, (mask.shape[1] // shrink, mask.shape[2] // shrink))


def read_frame(root: Path, frame: Frame, defaults: dict, downscale: int, checked: set) -> FrameImage:
    """The image, mask and lens of ``frame`` at ``downscale`` (``defaults``: the file's lens keys; ``checked``:
    the invertible lenses, ``check_invertible``); a DatasetError naming the frame and its file where the image
    is not the recorded size, its lens cannot be inverted, or its mask is not the image's size."""
    path, shrink, stored = image_file(root, frame, downscale)
    rgba = read_image(path, f"{frame.where}'s file_path")[None].float() / 255  # [1, H, W, 4]
    lens, recorded = frame_lens(frame, defaults, path, tuple(rgba.shape[1:3]), stored)
    check_invertible(lens, recorded, frame.where, checked)
    mask = frame_mask(root, frame, downscale)
    if shrink > 1:
        rgba = downscale_rgba(rgba, shrink)
    if mask is not None and mask.shape[1:] != rgba.shape[1:3]:
        raise DatasetError(f"{frame.where}: its mask is {mask.shape[2]}x{mask.shape[1]} pixels, its image "
                           f"{rgba.shape[2]}x{rgba.shape[1]}")
    return FrameImage(rgba, mask, lens.resized(recorded, tuple(rgba.shape[1:3])), Source(frame.where, path))


def check_one_size(first: FrameImage, image: FrameImage) -> None:
    """A DatasetError naming both files where ``image`` is not the size of the scene's ``first``."""
    if image.rgba.shape != first.rgba.shape:
        shape, first_shape = image.rgba.shape, first.rgba.shape
        raise DatasetError(f"{image.source.path}: image size {shape[2]}x{shape[1]} differs from "
                           f"{first.source.path} ({first_shape[2]}x{first_shape[1]}); nerfexp needs the images of a "
                           "scene in one size")


def stacked_views(images: list[FrameImage], c2w: Tensor) -> Views:
    """The ``images`` (one size) posed by ``c2w`` [N, 4, 4] as Views; where any has a mask, those without one
    count every pixel."""
    masks = [image.mask for image in images]
    if any(mask is not None for mask in masks):
        masks = [torch.ones(image.rgba.shape[1:3], dtype=torch.bool)[None] if image.mask is None else image.mask
                 for image in images]
    return Views(rgba=torch.cat([image.rgba for image in images]), c2w=c2w,
                 intrinsics=Intrinsics.stack([image.lens for image in images]),
                 mask=torch.cat(masks) if masks and masks[0] is not None else None,
                 sources=tuple(image.source for image in images))


@dataclass(kw_only=True)
class NerfstudioScene(FolderScene):
    """A scene in nerfstudio's format (``data=nerfstudio``): the module's docstring says how it is read.
    ``transforms``: the file's name in ``root``."""

    DOMAINS: ClassVar[dict[str, Rule]] = {**FolderScene.DOMAINS, "transforms": TEXT, "downscale": COUNT,
                                          "holdout": whole(2, INTEGER_LIMIT), "bound": FAR,
                                          "missing_images": choice(*MISSING_IMAGES)}

    transforms: str = TRANSFORMS
    downscale: int = 1
    holdout: int = 8
    bound: float = 4.0
    missing_images: str = "refuse"  # frames whose images do not exist: refused, or skip: left out (``with_images``)
    _posed: PosedCapture | None = field(default=None, init=False, repr=False)
    _bounds: tuple[float, float, str] | None = field(default=None, init=False, repr=False)

    def posed(self) -> PosedCapture:
        """The parsed transforms file with its poses normalized (``posed_capture``), read once and kept."""
        if self._posed is None:
            self._posed = posed_capture(self.folder(), self.transforms, self.downscale, self.bound, self.missing_images)
        return self._posed

    def frames_left_out(self) -> list[str] | None:
        """The frames left out for their missing images (``missing_images`` skip), by ``file_path``; None: none."""
        return list(self.posed().left_out) or None

    def capture(self) -> Capture:
        """The parsed transforms file (``posed``)."""
        return self.posed().capture

    def split_rule(self) -> str:
        """How the views were split: the file's lists, or every ``holdout``-th frame."""
        if self.capture().splits is not None:
            return f"the file's train_filenames / val_filenames / test_filenames ({self.transforms})"
        return f"every {self.holdout}th frame in file_path order a test view (data.holdout)"

    def split_index(self, split: str) -> Tensor:
        """The frames [K] of ``split``."""
        capture = self.capture()
        n = len(capture.frames)
        if capture.splits is None:
            return holdout_split(n, self.holdout, self.n_val, self.n_train)[split]
        names = [frame.file_path for frame in capture.frames]
        listed = capture.splits[split] or (capture.splits["test"][:self.n_val] if split == "val" else [])
        index = torch.tensor([names.index(name) for name in listed], dtype=torch.long)
        if split == "train" and self.n_train is not None:
            if self.n_train > len(index):
                raise DatasetError(f"data.n_train={self.n_train}: {capture.path} lists only {len(index)} training "
                                   "frames")
            index = index[:self.n_train]
        return index[:self.n_val] if split == "val" else index

    def ray_bounds(self) -> tuple[float, float]:
        """(near, far): the configured values where set, else the capture's (``found_bounds``)."""
        if self.near is not None and self.far is not None:
            return self.near, self.far
        near, far, _ = self.found_bounds()
        return (near if self.near is None else self.near), (far if self.far is None else self.far)

    def bounds_rule(self) -> str | None:
        """Where near and far came from (the module's docstring), or None where both are configured."""
        if self.near is not None and self.far is not None:
            return None
        rule = self.found_bounds()[2]
        if self.near is not None or self.far is not None:
            return f"data.{'near' if self.near is not None else 'far'} as configured; the other from {rule}"
        return rule

    def found_bounds(self) -> tuple[float, float, str]:
        """(near, far, rule): the first of the capture's sparse points, its scene box and the cameras' bound
        that bounds the frames' views (module docstring), found once and kept."""
        if self._bounds is None:
            floor = NEAR_FRACTION * self.bound
            for find in (self.point_bounds, self.box_bounds):
                found = find()
                if found is not None and found[1] > max(floor, found[0]):
                    self._bounds = (max(floor, found[0]), found[1], found[2] + f", near at least "
                                    f"{NEAR_FRACTION:g} x data.bound")
                    return self._bounds
            self._bounds = (floor, FAR_FACTOR * self.bound, f"the cameras' bound ({NEAR_FRACTION:g} and "
                            f"{FAR_FACTOR:g} x data.bound): the capture has no sparse points or scene box that its "
                            "cameras see")
        return self._bounds

    def frame_views(self) -> Tensor:
        """[N, 4, 3]: the view of every frame's camera, as normalized (``nerfexp.geometry.frusta.view_planes``),
        its lens at the image's recorded size (an image's header is read where the file gives no ``w, h``)."""
        posed = self.posed()
        capture = posed.capture
        root, planes = self.folder(), []
        for frame, c2w in zip(capture.frames, posed.c2w):
            size = None
            if "w" not in {**capture.defaults, **frame.fields} or "h" not in {**capture.defaults, **frame.fields}:
                path, _, stored = image_file(root, frame, self.downscale)
                height, width = image_size(path, f"{frame.where}'s file_path")
                size = (height * stored, width * stored)
            fields = frame_lens_fields(frame, capture.defaults, size)
            lens = read_lens_record(fields)
            planes.append(view_planes(c2w[None], Intrinsics.stack([lens]), int(fields["h"]), int(fields["w"])))
        return torch.cat(planes)

    def point_bounds(self) -> tuple[float, float, str] | None:
        """(near, far, rule) from the capture's sparse points (module docstring), or None where it has none
        that a camera sees."""
        posed = self.posed()
        capture, normalized = posed.capture, posed.c2w
        root = self.folder()
        if capture.ply_file is not None:
            path = scene_file(root, capture.ply_file)
            if not is_named_file(path, f"{capture.path}'s 'ply_file_path'"):
                raise DatasetError(f"{path} does not exist (named by {capture.path}'s 'ply_file_path')")
            points = (read_ply_points(path) - posed.centre) * posed.scale
            seen = in_view(points, normalized, self.frame_views())  # [N, P]
            bounds = near_far(normalized[:, :3, 3], points, [row.nonzero()[:, 0] for row in seen])
            if bounds is not None:
                return (*bounds, f"the sparse points of {path} ('ply_file_path'), each camera's points in its view")
        from nerfexp.data.colmap_sfm import find_model  # pycolmap: imported only where a capture may hold a model
        model = find_model(root)
        if model is not None:
            bounds = colmap_point_bounds(model, capture.frames, normalized)
            if bounds is not None:
                return (*bounds, f"the sparse points of the COLMAP model {model}")
        return None

    def box_bounds(self) -> tuple[float, float, str] | None:
        """(near, far, rule) from Instant-NGP's scene box (the nearest and farthest point of it in any frame's
        view), or None where the capture has none, or no camera sees it."""
        box = self.bounding_box()
        if box is None:
            return None
        nearest, farthest = box_reach(self.posed().c2w, self.frame_views(), box.double())
        seen = torch.isfinite(nearest)
        if not seen.any():
            return None
        return (nearest[seen].min().item(), farthest[seen].max().item(),
                "Instant-NGP's scene box ('aabb_scale'): its nearest and farthest point in the cameras' views")

    def bounding_box(self) -> Tensor | None:
        """[2, 3]: Instant-NGP's scene box (``ngp_box``) moved and scaled as the poses are; None without one."""
        posed = self.posed()
        if posed.capture.box is None:
            return None
        return ((posed.capture.box - posed.centre) * posed.scale).float()

    def views(self, split: str) -> Views:
        posed = self.posed()
        root = self.folder()
        index = self.split_index(split).tolist()
        check_images_exist([Source(frame.where, image_file(root, frame, self.downscale)[0])
                            for frame in posed.capture.frames])  # every split's, before any image is read
        images, checked = [], set()  # checked: the invertible lenses (``check_invertible``)
        for i in tqdm(index, desc=f"loading {split}", unit="image", disable=None):
            images.append(read_frame(root, posed.capture.frames[i], posed.capture.defaults, self.downscale, checked))
            check_one_size(images[0], images[-1])
        views = stacked_views(images, posed.c2w[index].float())
        factor = fit_factor(max(views.height, views.width), self.max_side)
        return views if factor == 1 else views.resized(downscale_rgba(views.rgba, factor))
