"""nerfstudio's data format (``transforms.json``), as ``ns-process-data`` writes it from photographs, video,
Polycam, Record3D, Metashape or ODM, and Instant-NGP's variant of it (``colmap2nerf.py``).

A scene root holds ``transforms.json``::

    {"camera_model": "OPENCV", "fl_x": 1072.0, "fl_y": 1068.0, "cx": 1504.0, "cy": 1000.0,
     "w": 3008, "h": 2000, "k1": 0.03, "k2": -0.02, "p1": 0.001, "p2": -0.001,
     "frames": [{"file_path": "images/frame_00001.jpg", "transform_matrix": <4x4 camera-to-world>,
                 "mask_path": "masks/frame_00001.png"}, ...],
     "applied_transform": <3x4>, "train_filenames": [...], "val_filenames": [...], "test_filenames": [...]}

Intrinsics (``fl_x fl_y cx cy w h``, ``camera_model`` and its coefficients: ``nerfexp.geometry.lens_records``)
are given at the top level, or per frame (a frame's key wins). Instant-NGP's files may give
``camera_angle_x`` (and ``camera_angle_y``) instead of ``fl_x`` (``fl_y``), leave out ``cx, cy`` (the image
centre), ``w, h`` (the image's size) and ``camera_model`` (``OPENCV`` where a coefficient is given, else a
pinhole), and add ``aabb_scale``, ``scale`` and ``offset`` (its scene box: ``ngp_box``). ``transform_matrix``
is nerfstudio's OpenGL convention (nerfexp's own, ``nerfexp.geometry.cameras``); ``applied_transform`` (the
transform nerfstudio applied to the poses it was given) is checked and kept as data (``Capture``).

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

import json
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import ClassVar

import torch
from torch import Tensor
from tqdm import tqdm

from nerfexp.data.base import Scene
from nerfexp.data.blender import FIELD_OF_VIEW, checked_frames, pose_matrix
from nerfexp.data.images import downscale_rgba, fit_factor, image_size, read_image
from nerfexp.data.sparse_points import near_far, read_ply_points
from nerfexp.data.views import SPLIT_NAMES, Source, Views, check_shared_file, holdout_split, shrink_mask
from nerfexp.domains import (
    COUNT,
    FAR,
    INTEGER_LIMIT,
    POSITION,
    POSITION_LIMIT,
    TEXT,
    Rule,
    bound_text,
    breaks,
    is_real,
    list_of,
    real,
    whole,
)
from nerfexp.errors import DatasetError
from nerfexp.files import atomic_write
from nerfexp.geometry.boxes import box_problem
from nerfexp.geometry.cameras import focal_from_fov, normalize_centres
from nerfexp.geometry.frusta import box_reach, in_view, view_planes
from nerfexp.geometry.lens_records import (
    FOCAL_RANGE,
    INTRINSIC_KEYS,
    LensRecordError,
    lens_record,
    read_lens_record,
)
from nerfexp.geometry.lenses import SLOTS, Intrinsics, inversion_problem
from nerfexp.pixels import png_bytes, to_uint8
from nerfexp.reading import UnreadableFile, read_json

TRANSFORMS = "transforms.json"
NEAR_FRACTION = 0.05  # near = 0.05 bound where not given
FAR_FACTOR = 2.0  # far = 2 bound where not given
SPLIT_KEYS = {"train": "train_filenames", "val": "val_filenames", "test": "test_filenames"}
NGP_SCALE, NGP_OFFSET = 0.33, (0.5, 0.5, 0.5)  # Instant-NGP's defaults for ``scale`` and ``offset``
# Instant-NGP's scene box keys (``ngp_box``); their bounds keep the arithmetic finite, the box itself is checked
NGP_BOX_KEYS = {"aabb_scale": ("a positive number at most 2^16 (a power of two up to 128 in Instant-NGP)",
                               real(0, 2 ** 16, above=True)[1]),
                "scale": ("a positive number at most 2^24", real(0, POSITION_LIMIT, above=True)[1]),
                "offset": ("a list of 3 numbers within +-2^24", list_of(POSITION, 3)[1])}


def write_nerfstudio(root: Path, splits: Iterable[tuple[str, Views]]) -> None:
    """Write the views of each ``(split, views)`` as they come (one split in memory at a time) as a scene in
    nerfstudio's format: ``root/images/{split}_{i:04d}.png`` (8-bit RGBA), their
    masks ``root/masks/{split}_{i:04d}.png`` (255 where a pixel counts) where the views have them, and
    ``root/transforms.json`` with every frame's pose and lens (``lens_record``: at the top level where all
    views share one, else per frame), ``w``, ``h`` and the splits' ``{split}_filenames``."""
    root = Path(root)
    frames, listed, lenses, size = [], {}, [], None
    for split, views in splits:
        size = views.rgba.shape[1:3]
        listed[SPLIT_KEYS[split]] = []
        for i, image in enumerate(to_uint8(views.rgba)):  # [H, W, 4] each
            name = f"{split}_{i:04d}.png"
            atomic_write(root / "images" / name, png_bytes(image))
            frame = {"file_path": f"images/{name}", "transform_matrix": views.c2w[i].double().tolist()}
            if views.mask is not None:
                atomic_write(root / "masks" / name, png_bytes(views.mask[i].numpy().astype("uint8") * 255))
                frame["mask_path"] = f"masks/{name}"
            frames.append(frame)
            lenses.append(lens_record(views.intrinsics[i]))
            listed[SPLIT_KEYS[split]].append(frame["file_path"])
    height, width = size
    shared = all(lens == lenses[0] for lens in lenses)
    for frame, lens in zip(frames, lenses):
        frame.update({} if shared else lens)
    content = {**(lenses[0] if shared else {}), "w": width, "h": height, "frames": frames, **listed}
    atomic_write(root / TRANSFORMS, json.dumps(content, indent=2).encode())


@dataclass
class Frame:
    """One frame of a transforms file: its ``file_path``, pose ``c2w`` [4, 4] float64 as stored, its own keys
    ``fields`` (the lens keys it overrides), ``mask_path`` or None, and ``where`` it is (file and frame)."""

    file_path: str
    c2w: Tensor
    fields: dict
    mask_path: str | None
    where: str


@dataclass
class Capture:
    """A parsed transforms file: its ``path``, the ``frames`` in ``file_path`` order, the top-level keys
    ``defaults`` of every frame's lens, the file's ``splits`` (lists of file paths) or None, its
    ``applied_transform`` [3 or 4, 4] or None, its scene ``box`` [2, 3] in the file's coordinates
    (``ngp_box``) or None, and its sparse points' PLY file ``ply_file`` (``ply_file_path``) or None."""

    path: Path
    frames: list[Frame]
    defaults: dict
    splits: dict[str, list[str]] | None
    applied_transform: Tensor | None
    box: Tensor | None
    ply_file: str | None = None


def is_pixel_side(value) -> bool:
    """An image's ``w`` or ``h``: a whole number of pixels from 1 to 2^24 (``FOCAL_RANGE``'s top: the lens's
    ``cx`` and ``cy``, half a side, are pixel coordinates within it), given as an integer or a float."""
    return is_real(value) and 1 <= value <= FOCAL_RANGE[1] and float(value).is_integer()


def relative_file(value, where: str, key: str) -> str:
    """A frame's file key: a string naming a file below the scene's folder (relative, no ``..``)."""
    if not isinstance(value, str) or not value.strip():
        raise DatasetError(f"{where}: '{key}' must be a file path relative to the scene's folder, got {value!r}")
    path = PurePosixPath(value.replace("\\", "/"))
    if path.is_absolute() or ".." in path.parts or (path.parts and ":" in path.parts[0]):
        raise DatasetError(f"{where}: '{key}' must be a path inside the scene's folder (relative, without '..'), "
                           f"got {value!r}")
    return value


def ngp_box(content: dict, where: str) -> Tensor | None:
    """Instant-NGP's scene box in the file's coordinates [2, 3], or None where ``aabb_scale`` is not given.
    Instant-NGP maps a position p to (p_y, p_z, p_x) ``scale`` + ``offset`` and bounds the scene by the cube
    of side ``aabb_scale`` centred on (0.5, 0.5, 0.5) there; mapped back, the cube's centre is
    ((0.5 - offset_z), (0.5 - offset_x), (0.5 - offset_y)) / scale and its half side aabb_scale / (2 scale).
    Each key keeps its rule (``NGP_BOX_KEYS``) and the box what an occupancy grid covers (``box_problem``),
    else a DatasetError names ``where``, the keys and their values."""
    if "aabb_scale" not in content:
        return None
    values = {"aabb_scale": content["aabb_scale"], "scale": content.get("scale", NGP_SCALE),
              "offset": content.get("offset", list(NGP_OFFSET))}
    for key, rule in NGP_BOX_KEYS.items():
        if (wanted := breaks(rule, values[key])) is not None:
            raise DatasetError(f"{where}: '{key}' must be {wanted}, got {values[key]!r:.80}")
    offset = torch.tensor(values["offset"], dtype=torch.float64)
    centre = (0.5 - offset[[2, 0, 1]]) / values["scale"]
    half = values["aabb_scale"] / (2 * values["scale"])
    box = torch.stack([centre - half, centre + half])
    if (problem := box_problem(box)) is not None:
        raise DatasetError(f"{where}: the scene box of {box_keys(values)}, {box.tolist()}, {problem}")
    return box


def box_keys(values: dict) -> str:
    """The keys that make Instant-NGP's scene box, with their ``values``, as an error names them."""
    return ", ".join(f"'{key}' {values[key]}" for key in NGP_BOX_KEYS)


def read_capture(path: Path) -> Capture:
    """The parsed transforms file ``path``, every key checked before any image is read (module docstring)."""
    try:
        content = read_json(path)  # bounded: a dataset from others
    except UnreadableFile as error:
        raise DatasetError(str(error)) from None
    if not isinstance(content, dict):
        raise DatasetError(f"{path}: expected a JSON object with the key 'frames'")
    lens_keys = {*INTRINSIC_KEYS, *SLOTS, "camera_model", "w", "h", "camera_angle_x", "camera_angle_y"}
    defaults = {key: content[key] for key in lens_keys if key in content}
    parsed = []
    for where, frame in checked_frames(path, content):
        file_path = relative_file(frame["file_path"], where, "file_path")
        mask = frame.get("mask_path")
        mask = None if mask is None else relative_file(mask, where, "mask_path")
        fields = {key: frame[key] for key in lens_keys if key in frame}
        parsed.append(Frame(file_path, pose_matrix(frame["transform_matrix"], where), fields, mask,
                            f"{where} ({file_path})"))
        frame_lens_fields(parsed[-1], defaults, None)  # checked now; the image's size is known later
    parsed.sort(key=lambda frame: frame.file_path)
    frame_of: dict[str, Frame] = {}  # each frame by its file's spelling (``spelling``)
    for frame in parsed:
        if (other := frame_of.setdefault(spelling(frame.file_path), frame)) is not frame:
            raise DatasetError(f"{other.where} and {frame.where} name one file: one view counted twice; list each "
                               "image once")
    splits = None
    if any(key in content for key in SPLIT_KEYS.values()):
        splits = {split: listed_frames(path, content, key, frame_of) for split, key in SPLIT_KEYS.items()}
        if not splits["train"] or not splits["test"]:
            raise DatasetError(f"{path}: 'train_filenames' and 'test_filenames' must both list frames where the "
                               "file lists its splits")
        check_disjoint_lists(path, splits)
    applied = content.get("applied_transform")
    if applied is not None:
        rows = isinstance(applied, list) and len(applied) in (3, 4) and all(map(list_of(POSITION, 4)[1], applied))
        if not rows:
            raise DatasetError(f"{path}: 'applied_transform' must be a 3x4 (or 4x4) list of finite numbers within "
                               f"+-2^24, got {applied!r:.80}")
        applied = torch.tensor(applied, dtype=torch.float64)
    ply_file = content.get("ply_file_path")
    ply_file = None if ply_file is None else relative_file(ply_file, str(path), "ply_file_path")
    return Capture(path, parsed, defaults, splits, applied, ngp_box(content, str(path)), ply_file)


def spelling(name: str) -> str:
    """One spelling of the relative file path ``name`` for all that name one file below the scene's folder:
    ``images//a.png``, ``images/./a.png`` and ``./images/a.png`` are ``images/a.png`` (as nerfstudio matches its
    split lists, by ``pathlib`` paths). ``scene_file`` reads the same file for each."""
    return str(PurePosixPath(name))


def listed_frames(path: Path, content: dict, key: str, frame_of: dict[str, Frame]) -> list[str]:
    """The ``file_path`` of each frame that ``content[key]`` (a split's list, e.g. 'test_filenames') names, in its
    order, matched by ``spelling``; a DatasetError naming the file and the key where the list is not a list of
    file paths, names a file no frame has, or names one frame twice."""
    listed = content.get(key, [])
    if not isinstance(listed, list) or not all(isinstance(name, str) for name in listed):
        raise DatasetError(f"{path}: '{key}' must be a list of file paths, got {listed!r:.80}")
    found: dict[str, str] = {}  # spelling -> the entry that named it first
    for name in listed:
        frame = frame_of.get(spelling(name))
        if frame is None:
            raise DatasetError(f"{path}: '{key}' names {name!r}, which no frame's 'file_path' is")
        if spelling(name) in found:
            raise DatasetError(f"{path}: '{key}' names {frame.where} twice ({found[spelling(name)]!r} and "
                               f"{name!r}): one view counted twice; list each image once")
        found[spelling(name)] = name
    return [frame_of[spelling(name)].file_path for name in listed]


def check_disjoint_lists(path: Path, splits: dict[str, list[str]]) -> None:
    """A DatasetError naming the file, both lists and the frame where a training frame is listed among the
    validation or test frames (validation may list test frames: ``nerfexp.data.views.MAY_SHARE``)."""
    training = set(splits["train"])
    for split in ("val", "test"):
        if shared := [name for name in splits[split] if name in training]:
            raise DatasetError(f"{path}: '{SPLIT_KEYS[split]}' and 'train_filenames' both list the frame "
                               f"{shared[0]!r}: a score on views training saw is no {SPLIT_NAMES[split]} score; "
                               "list each frame in one of them")


def frame_lens_fields(frame: Frame, defaults: dict, image_size: tuple[int, int] | None) -> dict:
    """The lens keys of ``frame`` (its own over the file's ``defaults``) completed as Instant-NGP completes
    them: ``fl_x`` from ``camera_angle_x`` and the width, ``fl_y`` from ``camera_angle_y`` or ``fl_x``,
    ``cx, cy`` the image's centre, ``camera_model`` OPENCV where a coefficient is given; ``w, h`` from the
    image (``image_size`` = (h, w); None: not read yet, only the keys given are checked). A DatasetError names
    the frame and the key."""
    merged = {**defaults, **frame.fields}
    for key in ("w", "h"):
        if key in merged and not is_pixel_side(merged[key]):
            raise DatasetError(f"{frame.where}: '{key}' must be a whole number of pixels, got {merged[key]!r:.80} "
                               f"(expected 1 to {bound_text(FOCAL_RANGE[1])})")
    for key in ("camera_angle_x", "camera_angle_y"):
        if key in merged and (wanted := breaks(FIELD_OF_VIEW, merged[key])) is not None:
            raise DatasetError(f"{frame.where}: '{key}' must be {wanted}, got {merged[key]!r:.80}")
    if "fl_x" not in merged and "camera_angle_x" not in merged:
        raise DatasetError(f"{frame.where}: missing key 'fl_x' (or Instant-NGP's 'camera_angle_x')")
    if image_size is None and ("w" not in merged or "h" not in merged):
        return merged
    height, width = (int(merged["h"]), int(merged["w"])) if "w" in merged and "h" in merged else image_size
    completed = {"cx": 0.5 * width, "cy": 0.5 * height, **merged}
    if "fl_x" not in completed:
        completed["fl_x"] = focal_from_fov(width, merged["camera_angle_x"])
    if "fl_y" not in completed:
        completed["fl_y"] = (focal_from_fov(height, merged["camera_angle_y"]) if "camera_angle_y" in merged
                             else completed["fl_x"])
    if "camera_model" not in completed:
        completed["camera_model"] = "OPENCV" if any(completed.get(key, 0) for key in SLOTS) else "PINHOLE"
    completed = {key: value for key, value in completed.items() if key not in ("camera_angle_x", "camera_angle_y")}
    try:
        read_lens_record(completed)
    except LensRecordError as error:
        raise DatasetError(f"{frame.where}: {error}") from None
    return {**completed, "w": width, "h": height}


def scene_file(root: Path, relative: str) -> Path:
    """The file a frame names: ``relative`` below ``root``; without an extension, ``.png`` (Blender's way)."""
    path = root / relative.removeprefix("./")
    return path if PurePosixPath(relative).suffix else path.with_name(path.name + ".png")


def downscaled_file(root: Path, relative: str, prefix: str, downscale: int) -> tuple[Path, int]:
    """The file to read for ``relative`` at ``downscale``, and the factor still to shrink it by:
    ``root/{prefix}_{d}/<file name>`` as ``ns-process-data`` writes it, where it exists (factor 1), else the
    full-size file (factor d)."""
    full = scene_file(root, relative)
    if downscale > 1:
        shrunk = root / f"{prefix}_{downscale}" / full.name
        if shrunk.is_file():
            return shrunk, 1
    return full, downscale


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
    spread = [torch.linalg.vector_norm(c - c.mean(0), dim=-1).square().mean().sqrt() for c in (ours, centres)]
    if not spread[1] > 0:
        return None
    points, observed = model_points(reconstruction, ids)
    bounds = near_far(centres, points, observed)
    ratio = (spread[0] / spread[1]).item()
    return None if bounds is None else (bounds[0] * ratio, bounds[1] * ratio)


def read_mask(path: Path, source: str) -> Tensor:
    """A mask image as bool [H, W]: True where the pixel counts (nonzero), as nerfstudio reads masks."""
    return read_image(path, source)[..., 0] > 0


@dataclass
class NerfstudioScene(Scene):
    """A scene in nerfstudio's format (``data=nerfstudio``): the module's docstring says how it is read.
    ``transforms``: the file's name in ``root``."""

    DOMAINS: ClassVar[dict[str, Rule]] = {**Scene.DOMAINS, "transforms": TEXT, "downscale": COUNT,
                                          "holdout": whole(2, INTEGER_LIMIT), "bound": FAR}

    root: str
    transforms: str = TRANSFORMS
    downscale: int = 1
    max_side: int | None = None
    n_train: int | None = None
    holdout: int = 8
    n_val: int = 2
    bound: float = 4.0
    near: float | None = None
    far: float | None = None
    background: str = "white"
    aabb: list | None = None
    density_noise_std: float = 0.0
    _capture: Capture | None = field(default=None, init=False, repr=False)
    _normalization: tuple[Tensor, Tensor, float] | None = field(default=None, init=False, repr=False)
    _bounds: tuple[float, float, str] | None = field(default=None, init=False, repr=False)

    def capture(self) -> Capture:
        """The parsed transforms file, read once and kept, and the normalization of its poses; a DatasetError
        where the scene box, normalized, is not one an occupancy grid covers (``box_problem``)."""
        if self._capture is None:
            root = Path(self.root)
            path = root / self.transforms
            if not path.is_file():
                raise DatasetError(f"{path} does not exist: data.root must be a folder holding {self.transforms} "
                                   f"(nerfstudio's format; data.transforms names another file in it)")
            capture = read_capture(path)
            check_shared_file([Source(frame.where, downscaled_file(root, frame.file_path, "images", self.downscale)[0])
                               for frame in capture.frames])
            c2w = torch.stack([frame.c2w for frame in capture.frames])
            normalized, _, centre, scale = normalize_centres(c2w, torch.zeros(0, 3, dtype=c2w.dtype), self.bound)
            box = None if capture.box is None else (capture.box - centre) * scale  # as bounding_box gives it
            if box is not None and (problem := box_problem(box)) is not None:
                raise DatasetError(f"{path}: the scene box of 'aabb_scale', 'scale' and 'offset', moved and scaled "
                                   f"as the poses are (data.bound={self.bound}), {box.tolist()}, {problem}")
            self._capture, self._normalization = capture, (normalized, centre, scale)
        return self._capture

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
        capture = self.capture()
        normalized, _, _ = self._normalization
        root, planes = Path(self.root), []
        for frame, c2w in zip(capture.frames, normalized):
            size = None
            if "w" not in {**capture.defaults, **frame.fields} or "h" not in {**capture.defaults, **frame.fields}:
                path, shrink = downscaled_file(root, frame.file_path, "images", self.downscale)
                stored = self.downscale if shrink == 1 else 1
                height, width = image_size(path, f"{frame.where}'s file_path")
                size = (height * stored, width * stored)
            fields = frame_lens_fields(frame, capture.defaults, size)
            lens = read_lens_record(fields)
            planes.append(view_planes(c2w[None], Intrinsics.stack([lens]), int(fields["h"]), int(fields["w"])))
        return torch.cat(planes)

    def point_bounds(self) -> tuple[float, float, str] | None:
        """(near, far, rule) from the capture's sparse points (module docstring), or None where it has none
        that a camera sees."""
        capture = self.capture()
        normalized, centre, scale = self._normalization
        root = Path(self.root)
        if capture.ply_file is not None:
            path = scene_file(root, capture.ply_file)
            if not path.is_file():
                raise DatasetError(f"{path} does not exist (named by {capture.path}'s 'ply_file_path')")
            points = (read_ply_points(path) - centre) * scale
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
        normalized, _, _ = self._normalization
        nearest, farthest = box_reach(normalized, self.frame_views(), box.double())
        seen = torch.isfinite(nearest)
        if not seen.any():
            return None
        return (nearest[seen].min().item(), farthest[seen].max().item(),
                "Instant-NGP's scene box ('aabb_scale'): its nearest and farthest point in the cameras' views")

    def bounding_box(self) -> Tensor | None:
        """[2, 3]: Instant-NGP's scene box (``ngp_box``) moved and scaled as the poses are; None without one."""
        box = self.capture().box
        if box is None:
            return None
        _, centre, scale = self._normalization
        return ((box - centre) * scale).float()

    def views(self, split: str) -> Views:
        capture = self.capture()
        normalized, _, _ = self._normalization
        root = Path(self.root)
        index = self.split_index(split).tolist()
        images, masks, lenses, sources, first = [], [], [], [], None
        invertible = set()  # the lenses (and image sizes) checked: most captures share one lens
        for i in tqdm(index, desc=f"loading {split}", unit="image", disable=None):
            frame = capture.frames[i]
            path, shrink = downscaled_file(root, frame.file_path, "images", self.downscale)
            image = read_image(path, f"{frame.where}'s file_path")[None].float() / 255  # [1, H, W, 4]
            height, width = image.shape[1:3]
            stored = self.downscale if shrink == 1 else 1  # a folder's images_{d} are stored d times smaller
            fields = frame_lens_fields(frame, capture.defaults, (height * stored, width * stored))
            recorded = (int(fields["h"]), int(fields["w"]))
            if abs(height * stored - recorded[0]) >= stored or abs(width * stored - recorded[1]) >= stored:
                raise DatasetError(f"{path}: image size {width}x{height} does not match {frame.where}'s w x h "
                                   f"{recorded[1]}x{recorded[0]}" + (f" shrunk by {stored}" if stored > 1 else ""))
            lens = read_lens_record(fields)
            key = (*lens.params.tolist(), *lens.distortion.tolist(), bool(lens.fisheye), *recorded)
            if key not in invertible:
                if problem := inversion_problem(lens, *recorded):
                    raise DatasetError(f"{frame.where}: {problem}")
                invertible.add(key)
            mask = None
            if frame.mask_path is not None:
                mask_file, mask_shrink = downscaled_file(root, frame.mask_path, "masks", self.downscale)
                mask = read_mask(mask_file, f"{frame.where}'s mask_path")[None]  # [1, H, W]
                if mask_shrink > 1:
                    mask = shrink_mask(mask, (mask.shape[1] // mask_shrink, mask.shape[2] // mask_shrink))
            if shrink > 1:
                image = downscale_rgba(image, shrink)
            if mask is not None and mask.shape[1:] != image.shape[1:3]:
                raise DatasetError(f"{frame.where}: its mask is {mask.shape[2]}x{mask.shape[1]} pixels, its image "
                                   f"{image.shape[2]}x{image.shape[1]}")
            if first is None:
                first = (path, image.shape)
            elif image.shape != first[1]:
                raise DatasetError(f"{path}: image size {image.shape[2]}x{image.shape[1]} differs from {first[0]} "
                                   f"({first[1][2]}x{first[1][1]}); nerfexp needs the images of a scene in one size")
            images.append(image)
            masks.append(mask)
            lenses.append(lens.resized(recorded, tuple(image.shape[1:3])))
            sources.append(Source(frame.where, path))
        if any(mask is not None for mask in masks):
            masks = [torch.ones(image.shape[1:3], dtype=torch.bool)[None] if mask is None else mask
                     for image, mask in zip(images, masks)]
        views = Views(rgba=torch.cat(images), c2w=normalized[index].float(), intrinsics=Intrinsics.stack(lenses),
                      mask=torch.cat(masks) if masks and masks[0] is not None else None, sources=tuple(sources))
        factor = fit_factor(max(views.height, views.width), self.max_side)
        return views if factor == 1 else views.resized(downscale_rgba(views.rgba, factor))
