"""Scenes posed by COLMAP (through pycolmap): a folder of photographs, or a video, in; posed ``Views`` out.

A scene root ``DIR`` holds ``images/`` (any depth; COLMAP names images by their path below it), or,
with ``data.video``, the images are frames taken from a video into ``DIR/frames/`` (the sharpest of
each 1/fps seconds, made once and cached: ``nerfexp.data.video``) and ``images/`` is not read. The
sparse model is taken from the first of these that exists, binary or text
(``cameras``, ``images``, ``points3D`` ``.bin`` or ``.txt``):

    DIR/sparse/0, DIR/sparse        a model you made yourself (COLMAP's usual layout)
    DIR/colmap/sparse/0             the model nerfexp made earlier (the cache)

and is otherwise made by ``reconstruct``: SIFT features, exhaustive or sequential matching
(``data.matcher``; by default sequential for a video's frames, which are in time order, and exhaustive
for photographs) and incremental mapping with one camera shared by all images, written to
``DIR/colmap/`` (the SQLite ``database.db`` and ``sparse/0``). Feature extraction shows progress per
image, matching and mapping per stage. Folders are built under a temporary name in ``DIR`` and renamed
into place when complete, so an interrupted run leaves no half-made cache; nothing outside
``DIR/colmap`` (and ``DIR/frames`` for a video) is ever written, and nothing is deleted but this run's
own temporary folder.

Conventions. COLMAP's poses are ``cam_from_world`` (x_cam = R x_world + t) for a camera that looks
down +z with y down; nerfexp's ``c2w`` looks down -z with y up (``nerfexp.geometry.cameras``):

    c2w = [[R^T, -R^T t], [0, 1]] @ diag(1, -1, -1, 1)

The world is then re-centred on the mean camera centre and scaled by s = bound / (the largest camera
distance from it), so every camera lies within ``bound`` of the origin; its orientation is COLMAP's.
Pixel centres are at (j + 0.5, i + 0.5) in both. ``near`` and ``far`` are ray distances (rays have
unit directions, so they are distances |X - c|, not depths z): over the images, 0.9 x the smallest
0.1th percentile and 1.1 x the largest 99.9th percentile of each image's distances to the sparse
points it observes (LLFF's percentiles). Surfaces without features have no points: a smooth object
nearer than every textured one can lie before ``near``; set ``data.near`` then. Tensors are float64
until ``Views`` are made.

Cameras are taken as COLMAP estimated them, one lens per image (``image_lenses``): any principal point,
fx and fy, and the distortion of every model ``nerfexp.geometry.lenses.PARAMETERS`` names, applied to the
rays (never by resampling the images); a lens whose distortion cannot be inverted over its image is
refused with a DatasetError.
"""

from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from nerfexp.data.base import FolderScene
from nerfexp.data.colmap_sfm import (
    find_model,
    image_files,
    read_model,
    reconstruct,
    registered_enough,
)
from nerfexp.data.images import downscale_rgba, fit_factor, read_image
from nerfexp.data.sparse_points import near_far
from nerfexp.data.video import FPS_RANGE, video_frames
from nerfexp.data.views import Source, Views, check_shared_file, holdout_split
from nerfexp.domains import (
    BOOLEAN,
    COUNT,
    FAR,
    INTEGER_LIMIT,
    PATH,
    POSITION_LIMIT,
    TEXT,
    THREADS,
    Applies,
    Rule,
    choice,
    expected,
    optional,
    real,
    whole,
)
from nerfexp.errors import DatasetError
from nerfexp.geometry.cameras import normalize_centres, pose_problem
from nerfexp.geometry.lens_records import COEFFICIENT_LIMIT, FOCAL_RANGE
from nerfexp.geometry.lenses import FISHEYE_MODELS, PARAMETERS, Intrinsics, distortion_vector, inversion_problem


def colmap_to_c2w(cam_from_world: Tensor) -> Tensor:
    """nerfexp camera-to-world matrices [N, 4, 4] from COLMAP's world-to-camera [R | t] [N, 3, 4].

    c2w = [[R^T, -R^T t], [0, 1]] @ diag(1, -1, -1, 1): the camera centre is -R^T t, and COLMAP's
    camera axes (x right, y down, looking down +z) become OpenGL's (x right, y up, looking down -z).
    Example: R = I, t = (0, 0, 4) -> centre (0, 0, -4), viewing direction -c2w[:3, 2] = (0, 0, 1).
    """
    R, t = cam_from_world[:, :, :3], cam_from_world[:, :, 3:]  # [N, 3, 3], [N, 3, 1]
    c2w = torch.zeros(len(R), 4, 4, dtype=cam_from_world.dtype)
    c2w[:, :3, :3] = R.transpose(1, 2) * torch.tensor([1.0, -1.0, -1.0], dtype=R.dtype)  # flips columns y, z
    c2w[:, :3, 3:] = -R.transpose(1, 2) @ t
    c2w[:, 3, 3] = 1
    return c2w


def cam_from_world(reconstruction, image_ids: list[int]) -> Tensor:
    """COLMAP's world-to-camera poses [R | t] [N, 3, 4] float64 of the images ``image_ids``."""
    return torch.tensor(np.stack([reconstruction.images[i].cam_from_world().matrix() for i in image_ids]))


def model_points(reconstruction, image_ids: list[int]) -> tuple[Tensor, list[Tensor]]:
    """(points [P, 3] float64, observed): a COLMAP model's 3D points, and for each image of ``image_ids`` the
    indices [K_i] of the points it observes (as ``near_far`` takes them)."""
    point_ids = sorted(reconstruction.point3D_ids())
    row = {point_id: k for k, point_id in enumerate(point_ids)}
    points = torch.tensor(np.array([reconstruction.points3D[p].xyz for p in point_ids]).reshape(-1, 3))
    observed = [torch.tensor([row[p.point3D_id] for p in reconstruction.images[i].get_observation_points2D()],
                             dtype=torch.long) for i in image_ids]
    return points, observed


def colmap_lens(model: str, params, where: str) -> Intrinsics:
    """The lens (shape []) of a COLMAP camera ``model`` with parameters ``params`` (COLMAP's order: f or
    fx, fy, then cx, cy, then the distortion coefficients ``lenses.PARAMETERS`` names), or a DatasetError
    naming ``where`` for a model nerfexp does not read or parameters out of a lens record's ranges
    (``nerfexp.geometry.lens_records``: ``FOCAL_RANGE``, ``COEFFICIENT_LIMIT``)."""
    if model not in PARAMETERS:
        raise DatasetError(f"{where}: camera model {model} is not one nerfexp reads ({', '.join(PARAMETERS)})")
    names = PARAMETERS[model]
    params = [float(v) for v in params]
    lead = params[:len(params) - len(names)]  # (f, cx, cy) or (fx, fy, cx, cy)
    fx, fy, cx, cy = (lead[0], *lead) if len(lead) == 3 else lead
    focal, centre = FOCAL_RANGE, (-FOCAL_RANGE[1], FOCAL_RANGE[1])  # NaN is in no range
    if not (all(focal[0] <= f <= focal[1] for f in (fx, fy)) and all(centre[0] <= c <= centre[1] for c in (cx, cy))
            and all(abs(k) <= COEFFICIENT_LIMIT for k in params[len(lead):])):
        raise DatasetError(f"{where}: camera parameters {params}: expected focal lengths in [2^-24, 2^24] pixels, a "
                           f"principal point within +-2^24 pixels and coefficients within +-{COEFFICIENT_LIMIT:g}")
    distortion = distortion_vector(dict(zip(names, params[len(lead):])))
    return Intrinsics(torch.tensor([fx, fy, cx, cy], dtype=torch.float64), distortion,
                      torch.tensor(model in FISHEYE_MODELS))


def image_lenses(reconstruction, image_ids: list[int], where: Path) -> tuple[Intrinsics, int, int]:
    """(lenses [N], width, height) of the images ``image_ids``: each image's camera as it is (any principal
    point, fx and fy, distortion), checked to be invertible over the image (``inversion_problem``); the
    images must share one size."""
    cameras = {camera_id: reconstruction.camera(camera_id) for camera_id in
               sorted({reconstruction.images[i].camera_id for i in image_ids})}
    sizes = {(camera.width, camera.height) for camera in cameras.values()}
    if len(sizes) > 1:
        raise DatasetError(f"{where}: the images' cameras have {len(sizes)} image sizes ({sorted(sizes)}); nerfexp "
                           "needs images of one size")
    lenses = {}
    for camera_id, camera in cameras.items():
        lens = colmap_lens(camera.model.name, camera.params, f"{where}: camera {camera_id}")
        if problem := inversion_problem(lens, camera.height, camera.width):
            raise DatasetError(f"{where}: camera {camera_id} ({camera.model.name}): {problem}")
        lenses[camera_id] = lens
    width, height = sizes.pop()
    return Intrinsics.stack([lenses[reconstruction.images[i].camera_id] for i in image_ids]), width, height


C_INT_LIMIT = 2 ** 31 - 1  # COLMAP's counts (features per image): its C ints



@dataclass
class ColmapData:
    """A posed COLMAP scene: ``names`` of the N registered images in name order, in ``image_dir``;
    ``c2w`` [N, 4, 4] float64 normalized; each image's lens ``intrinsics`` [N], the images' ``width`` and
    ``height``;
    the ray bounds ``near``, ``far``; the normalization x -> ``scale`` (x - ``centre``)."""

    names: list[str]
    image_dir: Path
    c2w: Tensor
    intrinsics: Intrinsics
    width: int
    height: int
    near: float
    far: float
    centre: Tensor
    scale: float


def load_colmap(root, bound: float = 4.0, camera_model: str = "SIMPLE_RADIAL", matcher: str | None = None,
                max_features: int = 4096, threads: int = -1, min_registered: float = 0.8,
                verbose: bool = False, video: str | None = None, fps: float = 2.0) -> ColmapData:
    """The scene ``root`` posed. Its images are ``root/images``, or with ``video`` (a path relative to
    ``root``, or absolute) the video's sharpest frame of each 1/``fps`` seconds (``video_frames``, cached
    in ``root/frames``). Its model is found (``find_model``) or made (``reconstruct``, ``matcher`` None:
    sequential for a video's frames, which are in time order, else exhaustive), undistorted where its
    camera has distortion, converted, normalized into ``bound`` and bounded by its points."""
    root = Path(root)
    if video is None:
        source_dir = root / "images"
        if not source_dir.is_dir():
            raise DatasetError(f"{source_dir} does not exist: data.root must be a folder holding images/ (and "
                               f"optionally a COLMAP model in sparse/0), or set data.video")
    else:
        source_dir = video_frames(root, video, fps)
    matcher = matcher or ("exhaustive" if video is None else "sequential")
    n_images = len(image_files(source_dir))
    model_dir = find_model(root) or reconstruct(root, camera_model, matcher, max_features, threads, min_registered,
                                                verbose, source_dir)
    reconstruction = read_model(model_dir)
    ids = sorted(reconstruction.reg_image_ids(), key=lambda i: reconstruction.images[i].name)
    registered_enough(len(ids), max(n_images, len(ids)), min_registered, f"{source_dir} (model {model_dir})")
    intrinsics, width, height = image_lenses(reconstruction, ids, model_dir)
    points, observed = model_points(reconstruction, ids)
    poses = colmap_to_c2w(cam_from_world(reconstruction, ids))
    for i, pose in zip(ids, poses):
        if (problem := pose_problem(pose)) is not None:
            raise DatasetError(f"{model_dir}: image {i} ({reconstruction.images[i].name}): the pose must be a rigid "
                               f"camera pose, but {problem}")
    if not bool((points.abs() <= POSITION_LIMIT).all()):  # NaN is not
        raise DatasetError(f"{model_dir}: a 3D point that is not finite or lies more than 2^24 scene units from the "
                           "origin, where float32 positions have no sub-unit resolution")
    c2w, points, centre, scale = normalize_centres(poses, points, bound)
    bounds = near_far(c2w[:, :3, 3], points, observed)
    if bounds is None:
        raise DatasetError(f"{model_dir}: the COLMAP model has no 3D points seen by its images: near and far are "
                           "undefined")
    near, far = bounds
    names = [reconstruction.images[i].name for i in ids]
    return ColmapData(names, source_dir, c2w, intrinsics, width, height, near, far, centre, scale)


def read_views(data: ColmapData, index: Tensor, downscale: int = 1, max_side: int | None = None) -> Views:
    """The images ``index`` of ``data`` as opaque ``Views``, shrunk by ``downscale`` and then, where
    ``max_side`` is set, by the smallest further integer factor that brings the longer side to at most
    ``max_side``; the lenses follow the images' size (``Intrinsics.resized``)."""
    shrink = downscale * fit_factor(max(data.width, data.height) // downscale, max_side)
    sources = tuple(Source(str(data.image_dir / data.names[i]), data.image_dir / data.names[i]) for i in index.tolist())
    check_shared_file(sources)
    images = []
    for i in tqdm(index.tolist(), desc="loading colmap", unit="image", disable=None):
        path = data.image_dir / data.names[i]
        image = read_image(path, f"the COLMAP model's image {data.names[i]!r}")
        if image.shape[:2] != (data.height, data.width):
            raise DatasetError(f"{path}: image size {image.shape[1]}x{image.shape[0]} is not the COLMAP camera's "
                               f"{data.width}x{data.height}")
        rgba = image[None].float() / 255  # [1, H, W, 4]
        images.append(downscale_rgba(rgba, shrink) if shrink > 1 else rgba)
    rgba = torch.cat(images) if images else torch.zeros(0, data.height // shrink, data.width // shrink, 4)
    intrinsics = data.intrinsics[index].resized((data.height, data.width), tuple(rgba.shape[1:3]))
    return Views(rgba=rgba, c2w=data.c2w[index].float(), intrinsics=intrinsics, sources=sources)


@dataclass(kw_only=True)
class ColmapScene(FolderScene):
    """Photographs, or the frames of a video, posed by COLMAP (``data=colmap``); see the module's
    docstring for the cache, the conventions and the normalization. ``video``: a video file relative to
    ``root`` (or absolute) whose sharpest frame of each 1/``fps`` seconds is taken instead of
    ``root/images`` (``nerfexp.data.video``). ``matcher`` None: sequential for a video, else exhaustive.
    Test views are every ``holdout``-th image in name order, training views the first ``n_train`` of the
    rest, validation views the first ``n_val`` test views. ``near`` and ``far`` None: from the sparse
    points (``ray_bounds()``)."""

    DOMAINS: ClassVar[dict[str, Rule]] = {
        **FolderScene.DOMAINS,
        "video": optional(PATH, "the photographs in images/"),
        "fps": real(*FPS_RANGE),
        "downscale": COUNT,
        "holdout": whole(2, INTEGER_LIMIT),
        "bound": FAR,
        "camera_model": TEXT,  # COLMAP's model names (checked against pycolmap's list when it runs)
        "matcher": optional(choice("exhaustive", "sequential"), "sequential for a video, else exhaustive"),
        "max_features": whole(1, C_INT_LIMIT),
        # at most THREAD_LIMIT (more than any machine); above the CPUs this process may use: capped at them
        "threads": (f"-1 (every CPU this process may use) or {expected(THREADS)}",
                    lambda v: v == -1 or THREADS[1](v)),
        "min_registered": real(0, 1, above=True),
        "verbose": BOOLEAN,
    }
    APPLIES: ClassVar[dict[str, Applies]] = {  # nerfexp.domains: when an argument does nothing
        **FolderScene.APPLIES,
        "fps": lambda scene: None if scene.get("video") is not None else "data.video=null (photographs, not a video)",
    }

    video: str | None = None
    fps: float = 2.0
    downscale: int = 1
    holdout: int = 8
    bound: float = 4.0
    camera_model: str = "SIMPLE_RADIAL"
    matcher: str | None = None
    max_features: int = 4096
    threads: int = -1
    min_registered: float = 0.8
    verbose: bool = False
    _data: ColmapData | None = field(default=None, init=False, repr=False)

    def load(self) -> ColmapData:
        """The posed scene, reconstructed or read once and kept."""
        for name in ("downscale", "holdout", "max_side"):
            value = getattr(self, name)
            lowest = 2 if name == "holdout" else 1
            if value is not None and value < lowest:
                raise DatasetError(f"data.{name} must be >= {lowest}, got {value}")
        if not self.bound > 0:
            raise DatasetError(f"data.bound must be positive, got {self.bound}")
        if self._data is None:
            self._data = load_colmap(self.folder(), self.bound, self.camera_model, self.matcher, self.max_features,
                                     self.threads, self.min_registered, self.verbose, self.video, self.fps)
        return self._data

    def ray_bounds(self) -> tuple[float, float]:
        """(near, far): the configured values where set, else the sparse points' (see ``near_far``)."""
        data = self.load()
        return (data.near if self.near is None else self.near), (data.far if self.far is None else self.far)

    def bounds_rule(self) -> str | None:
        if self.near is not None and self.far is not None:
            return None
        return "the COLMAP model's sparse points, each image's points it observes"

    def split_rule(self) -> str:
        return f"every {self.holdout}th image in name order a test view (data.holdout)"

    def views(self, split: str) -> Views:
        data = self.load()
        index = holdout_split(len(data.names), self.holdout, self.n_val, self.n_train)[split]
        return read_views(data, index, self.downscale, self.max_side)
