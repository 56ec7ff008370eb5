"""nerfstudio's data format, the file ``transforms.json``, as ``ns-process-data`` writes it from photographs,
video, Polycam, Record3D, Metashape or ODM, and Instant-NGP's variant of it (``colmap2nerf.py``): the file parsed
and checked (``read_capture``), and written (``write_nerfstudio``). How a scene is read from it (images, splits,
poses, ray bounds): ``nerfexp.data.nerfstudio``.

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

Parsing (``read_capture``): frames in ``file_path`` order (as nerfstudio orders them); ``file_path`` and
``mask_path`` relative to the root (no absolute path, no ``..``); the split lists' entries matched to frames by
``spelling``, a frame listed twice or in ``train_filenames`` and another list refused (validation may list test
frames). Every malformed field is a DatasetError naming the file, the frame and the key, before any image is read.
"""

import json
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import torch
from torch import Tensor

from nerfexp.data.blender import FIELD_OF_VIEW, checked_frames, pose_matrix
from nerfexp.data.views import SPLIT_NAMES, Views, is_named_file
from nerfexp.domains import POSITION, POSITION_LIMIT, bound_text, breaks, is_real, list_of, real
from nerfexp.errors import DatasetError
from nerfexp.files import atomic_write
from nerfexp.geometry.boxes import box_problem
from nerfexp.geometry.cameras import focal_from_fov
from nerfexp.geometry.lens_records import FOCAL_RANGE, INTRINSIC_KEYS, LensRecordError, lens_record, read_lens_record
from nerfexp.geometry.lenses import SLOTS
from nerfexp.pixels import png_bytes, to_uint8
from nerfexp.reading import UnreadableFile, name_problem, read_json

TRANSFORMS = "transforms.json"
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
    if (problem := name_problem(value)) is not None:
        raise DatasetError(f"{where}: '{key}' {problem}, got {value!r:.80}")
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


def downscaled_file(root: Path, relative: str, prefix: str, downscale: int, named_by: str) -> tuple[Path, int]:
    """The file to read for ``relative`` (which ``named_by`` names) at ``downscale``, and the factor still to shrink
    it by: ``root/{prefix}_{d}/<file name>`` as ``ns-process-data`` writes it, where it exists (factor 1), else the
    full-size file (factor d)."""
    full = scene_file(root, relative)
    if downscale > 1:
        shrunk = root / f"{prefix}_{downscale}" / full.name
        if is_named_file(shrunk, named_by):
            return shrunk, 1
    return full, downscale
