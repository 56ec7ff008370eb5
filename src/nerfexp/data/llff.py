"""The LLFF format of real forward-facing scenes (the NeRF paper's "Real Forward-Facing" data).

A scene folder holds ``images/`` (the photographs, in file-name order; optionally shrunk copies in
``images_{factor}/``) and ``poses_bounds.npy``, a float array [N, 17], one row per image: a 3x5
matrix flattened row-major, then the near and far depth bounds of the scene seen from that camera.
The 3x5 matrix's columns are the camera's axes in LLFF's [down, right, backwards] order, its centre,
and [H, W, focal] (image height and width in pixels, focal length in pixels at that size).

Loading (``load_llff``), as in the NeRF authors' code:

1. axes to nerfexp's OpenGL convention ([right, up, backwards], ``nerfexp.geometry.cameras``):
   [down, right, back] -> [right, -down, back];
2. scale: translations and bounds times s = 1 / (0.75 min(bounds)), so the nearest depth is 4/3 and
   the near plane z = -1 of NDC (``NDC_NEAR``) lies in front of everything;
3. re-centre: every pose is expressed in the frame of the average camera (``average_pose``), whose
   rotation becomes the identity and centre the origin, so the scene lies down -z;
4. every ``holdout``-th image (i % holdout == 0) is a test view, the rest train; val: the first
   ``n_val`` test views.

Tensors: ``c2w`` [N, 4, 4] camera-to-world, ``bounds`` [N, 2] (near, far depth), float64 until the
images are made ``Views``.
"""

import io
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from nerfexp.data.base import FolderScene
from nerfexp.data.images import downscale_rgba, fit_factor, read_image
from nerfexp.data.views import IMAGE_SUFFIXES, Source, Views, check_shared_file, holdout_split
from nerfexp.domains import BOOLEAN, COUNT, INTEGER_LIMIT, POSITION_LIMIT, Rule, whole
from nerfexp.errors import ConfigError, DatasetError
from nerfexp.files import atomic_write
from nerfexp.geometry.cameras import look_at, pose_problem
from nerfexp.geometry.lens_records import FOCAL_RANGE
from nerfexp.geometry.lenses import Intrinsics, corner_pixels, pixel_rays
from nerfexp.geometry.ndc import ndc_rays
from nerfexp.pixels import png_bytes, to_uint8

POSES_BOUNDS = "poses_bounds.npy"
BOUNDS_MARGIN = 0.75  # the nearest bound is scaled to 1 / 0.75
NDC_NEAR = 1.0  # the near plane z = -1 of NDC rays, in front of the scaled scene's nearest depth 4/3
LAYOUT = (f"an LLFF scene holds {POSES_BOUNDS} (N x 17: per image a 3x5 matrix [down, right, back, centre, "
          "(H, W, focal)] row-major, then near and far depth) and images/ (N images, in file-name order)")


def read_poses_bounds(path: Path) -> tuple[Tensor, Tensor]:
    """The rows of a ``poses_bounds.npy``: (poses [N, 3, 5], bounds [N, 2]), float64, as stored.

    Raises a DatasetError naming the file unless it is a finite N x 17 array with 0 < near < far <= 2^24,
    H and W whole numbers of pixels up to 2^24 and focal in ``FOCAL_RANGE`` in every row, the same in all, and a
    rigid pose in every row.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path} does not exist: {LAYOUT}")
    try:
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as error:
        raise DatasetError(f"{path}: not a NumPy .npy array ({error})") from None
    if array.ndim != 2 or array.shape[1] != 17 or array.shape[0] == 0 or array.dtype.kind not in "fiu":
        raise DatasetError(f"{path}: expected a numeric N x 17 array (per image a 3x5 pose matrix row-major, "
                           f"then near and far depth), got {array.dtype} of shape {array.shape}")
    rows = torch.from_numpy(array.astype(np.float64))
    bad = ~torch.isfinite(rows).all(-1)
    if bad.any():
        raise DatasetError(f"{path}: row {int(bad.nonzero()[0])} holds a NaN or infinite value")
    poses, bounds = rows[:, :15].reshape(-1, 3, 5), rows[:, 15:]
    bad = ~((bounds[:, 0] > 0) & (bounds[:, 1] > bounds[:, 0]) & (bounds[:, 1] <= POSITION_LIMIT))
    if bad.any():
        i = int(bad.nonzero()[0])
        raise DatasetError(f"{path}: row {i}: depth bounds must satisfy 0 < near < far <= 2^24 (scene units), got "
                           f"{bounds[i].tolist()}")
    hwf = poses[:, :, 4]
    sides, focal = hwf[:, :2], hwf[:, 2]
    bad = ~(((sides >= 1) & (sides <= FOCAL_RANGE[1]) & (sides == sides.round())).all(-1)
            & (focal >= FOCAL_RANGE[0]) & (focal <= FOCAL_RANGE[1]))
    if bad.any():
        i = int(bad.nonzero()[0])
        raise DatasetError(f"{path}: row {i}: height, width and focal must be positive (height and width whole "
                           f"numbers of pixels up to 2^24, focal in [2^-24, 2^24] pixels), got {hwf[i].tolist()}")
    if not (hwf == hwf[0]).all():  # one camera: nerfexp's Views share one focal length
        raise DatasetError(f"{path}: every row must record the same height, width and focal (one camera), "
                           f"got {hwf.unique(dim=0).tolist()[:3]}")
    for i, c2w in enumerate(llff_to_c2w(poses)):
        if (problem := pose_problem(c2w)) is not None:
            raise DatasetError(f"{path}: row {i}: the pose must be a rigid camera pose, but {problem}")
    return poses, bounds


def llff_to_c2w(poses: Tensor) -> Tensor:
    """LLFF 3x5 matrices [N, 3, 5] -> OpenGL camera-to-world [N, 4, 4]: axes [down, right, back] -> [right, up,
    back]."""
    down, right, back, centre = poses[..., :4].unbind(-1)
    c2w = torch.zeros(*poses.shape[:-2], 4, 4, dtype=poses.dtype)
    c2w[..., :3, :] = torch.stack([right, -down, back, centre], -1)
    c2w[..., 3, 3] = 1
    return c2w


def c2w_to_llff(c2w: Tensor, height: int, width: int, focal: float) -> Tensor:
    """OpenGL camera-to-world [N, 4, 4] -> LLFF 3x5 matrices [N, 3, 5] (the inverse of ``llff_to_c2w``)."""
    right, up, back, centre = c2w[..., :3, :4].unbind(-1)
    hwf = torch.tensor([height, width, focal], dtype=c2w.dtype).expand_as(centre)
    return torch.stack([-up, right, back, centre, hwf], -1)


def average_pose(c2w: Tensor) -> Tensor:
    """The average camera [4, 4] of cameras ``c2w`` [N, 4, 4]: at their mean centre, looking down the
    normalized sum of their viewing directions, with the up direction nearest their summed up axes."""
    centre = c2w[:, :3, 3].mean(0)
    back, up = c2w[:, :3, 2].sum(0), c2w[:, :3, 1].sum(0)
    return look_at(centre, centre - back, up)


def normalize_poses(c2w: Tensor, bounds: Tensor) -> tuple[Tensor, Tensor, float]:
    """Scale by s = 1 / (0.75 min(bounds)) (translations and bounds), then re-centre on the average camera.

    c2w [N, 4, 4], bounds [N, 2] -> (inverse(average) @ scaled c2w [N, 4, 4], s bounds [N, 2], s).
    """
    scale = 1.0 / (BOUNDS_MARGIN * bounds.min().item())
    scaled = c2w.clone()
    scaled[:, :3, 3] *= scale
    return torch.linalg.inv(average_pose(scaled)) @ scaled, bounds * scale, scale



def image_files(folder: Path, n_expected: int, poses_path: Path) -> list[Path]:
    """The images of ``folder`` in file-name order; a DatasetError unless there are ``n_expected``."""
    if not folder.is_dir():
        raise DatasetError(f"{folder} does not exist: {LAYOUT}")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))
    if len(files) != n_expected:
        raise DatasetError(f"{folder} holds {len(files)} images ({', '.join(IMAGE_SUFFIXES)}) but {poses_path} "
                           f"has {n_expected} rows: one row per image, in file-name order")
    return files


@dataclass
class LLFFData:
    """A loaded LLFF scene: all N images as ``views`` (processed poses), their scaled ``bounds`` [N, 2],
    the ``scale`` s applied to translations and bounds, and the image indices of each split."""

    views: Views
    bounds: Tensor
    scale: float
    splits: dict[str, Tensor]

    def split(self, name: str) -> Views:
        index = self.splits[name]
        return self.views.subset(index)


def read_images(files: list[Path], poses_path: Path, size: tuple[float, float], factor: int,
                max_side: int | None) -> Tensor:
    """The images ``files`` as straight-alpha RGBA [N, h, w, 4] in [0, 1] (opaque where a file has no
    alpha), each area-averaged (``downscale_rgba``) by ``factor``, and then by the smallest further integer
    factor that brings the longer side to at most ``max_side``. ``size`` is the (height, width) that
    ``poses_path`` records: the images must have its aspect ratio (to within a pixel) and all one size."""
    height, width = size
    images, first = [], None
    for i, path in enumerate(tqdm(files, desc="loading llff", unit="image", disable=None)):
        image = read_image(path, f"row {i} of {poses_path}")
        if first is None:
            first = (path, image.shape)
            h, w = image.shape[:2]
            if abs(h * width - w * height) > max(width, height):  # aspect ratios differ by more than a pixel
                raise DatasetError(f"{path}: image size {w}x{h} has not the aspect ratio of the size "
                                   f"{width:g}x{height:g} that {poses_path} records")
            factor *= fit_factor(max(h, w) // factor, max_side)
        elif image.shape != first[1]:
            (h, w), (h0, w0) = image.shape[:2], first[1][:2]
            raise DatasetError(f"{path}: image size {w}x{h} differs from {first[0]} ({w0}x{h0}); all images must match")
        rgba = image[None].float() / 255  # [1, H, W, 4]
        images.append(downscale_rgba(rgba, factor) if factor > 1 else rgba)
    return torch.cat(images)


def load_llff(root, factor: int = 1, holdout: int = 8, n_val: int = 2, max_side: int | None = None,
              n_train: int | None = None) -> LLFFData:
    """Load an LLFF scene, its images shrunk by the integer ``factor`` (``images_{factor}/`` as they are
    where that folder exists, else ``images/`` area-averaged), and then, where ``max_side`` is set, by
    the smallest further integer factor that brings the longer side to at most ``max_side`` pixels.

    The focal length is the recorded one times (loaded width / recorded width): focal / factor when
    the factor divides the width, and still right for images stored at another resolution. Splits:
    ``holdout_split`` (``n_train``: the first that many training views; None: all).
    """
    for name, value in (("factor", factor), ("max_side", max_side)):
        if value is not None and value < 1:
            raise DatasetError(f"{name} must be >= 1, got {value}")
    if holdout < 2:
        raise DatasetError(f"holdout must be >= 2 (every holdout-th image is a test view), got {holdout}")
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"data.root {root} does not exist: set the config key data.root to a folder where {LAYOUT}")
    poses_path = root / POSES_BOUNDS
    poses, bounds = read_poses_bounds(poses_path)
    shrunk = root / f"images_{factor}"
    folder, shrink = (shrunk, 1) if factor > 1 and shrunk.is_dir() else (root / "images", factor)
    height, width, focal = poses[0, :, 4].tolist()
    files = image_files(folder, len(poses), poses_path)
    sources = tuple(Source(f"{path} (row {i} of {poses_path})", path) for i, path in enumerate(files))
    check_shared_file(sources)
    rgba = read_images(files, poses_path, (height, width), shrink, max_side)
    c2w, bounds, scale = normalize_poses(llff_to_c2w(poses), bounds)
    recorded = Intrinsics.pinhole(focal, height, width, (len(poses),))  # LLFF's one centred pinhole, as recorded
    views = Views(rgba=rgba, c2w=c2w.float(), intrinsics=recorded.resized((height, width), rgba.shape[1:3]),
                  sources=sources)
    return LLFFData(views=views, bounds=bounds, scale=scale, splits=holdout_split(len(poses), holdout, n_val, n_train))


def write_llff(root, images: Tensor, c2w: Tensor, focal: float, bounds: Tensor) -> None:
    """Write a scene in the LLFF format: ``root/images/{i:03d}.png`` and ``root/poses_bounds.npy``.

    images [N, H, W, 3] in [0, 1] (saved as 8-bit), c2w [N, 4, 4] OpenGL camera-to-world,
    ``focal`` in pixels, bounds [N, 2] the near and far depth of what each camera sees.
    """
    root = Path(root)
    N, H, W, _ = images.shape  # views, rows, columns, channels
    digits = max(3, len(str(N - 1)))
    for i, image in enumerate(to_uint8(images)):  # [H, W, 3] each
        atomic_write(root / "images" / f"{i:0{digits}d}.png", png_bytes(image))
    poses = c2w_to_llff(c2w.to(torch.float64), H, W, focal)  # [N, 3, 5]
    rows = torch.cat([poses.reshape(N, 15), bounds.to(torch.float64)], -1).numpy()
    buffer = io.BytesIO()
    np.save(buffer, rows)
    atomic_write(root / POSES_BOUNDS, buffer.getvalue())


def holdout_rule(holdout: int) -> str:
    """How a scene of this format chose its test views (results.json's ``split``): every ``holdout``-th image."""
    return f"every {holdout}th image in file-name order a test view (data.holdout)"


def check_forward_facing(views: Views) -> None:
    """A DatasetError unless every ray of every view looks down -z (d_z < 0), as NDC needs.

    A ray's d_z is linear in the pixel position, so the four corner pixels' rays decide it.
    """
    H, W = views.height, views.width
    corners = pixel_rays(corner_pixels(H, W), views.intrinsics.unsqueeze(1))  # [N, 4, 3]: the corner pixels' rays
    dz = (views.c2w[:, None, 2, :3] * corners.to(views.c2w.dtype)).sum(-1)  # [N, 4]: the world z of each corner ray
    bad = (dz >= 0).any(-1)
    if bad.any():
        i = int(bad.nonzero()[0])
        raise DatasetError(f"data.ndc=true needs forward-facing cameras (every ray looking down -z after "
                           f"re-centring), but the rays of image {i} reach d_z = {dz[i].max().item():.2f}; "
                           "set data.ndc=false with data.near and data.far for this scene")


@dataclass(kw_only=True)
class LLFFScene(FolderScene):
    """An LLFF-format scene (``data=llff``): test views every ``holdout``-th image, training views the
    first ``n_train`` of the rest (None: all), validation the first ``n_val`` test views.

    With ``ndc`` the model renders NDC rays (``nerfexp.geometry.ndc``) with t in [near, far] = [0, 1], from
    the near plane to infinity; without it, world rays with t in [near, far] in the scaled scene's
    units, which must enclose the scaled depth bounds.
    """

    DOMAINS: ClassVar[dict[str, Rule]] = {**FolderScene.DOMAINS, "factor": COUNT, "holdout": whole(2, INTEGER_LIMIT),
                                          "ndc": BOOLEAN}

    @staticmethod
    def NDC(config: Mapping) -> tuple[tuple[str, ...], tuple[str, ...]]:
        """``ndc`` where set: its rays are NDC rays; world rays need ``near`` and ``far`` instead."""
        return (("ndc",), ("near", "far")) if config.get("ndc") else ((), ())

    factor: int = 4
    holdout: int = 8
    ndc: bool = True
    near: float = 0.0  # NDC's: the near plane to infinity
    far: float = 1.0
    background: str = "black"
    density_noise_std: float = 1.0  # the paper's for real forward-facing captures
    _data: LLFFData | None = field(default=None, init=False, repr=False)

    def load(self) -> LLFFData:
        """All images and poses, loaded once and kept."""
        if self._data is None:
            data = load_llff(self.folder(), self.factor, self.holdout, self.n_val, self.max_side, self.n_train)
            if self.ndc:
                check_forward_facing(data.views)
            else:
                low, high = data.bounds.min().item(), data.bounds.max().item()
                if not self.near <= low < high <= self.far:
                    raise ConfigError(f"data.near={self.near:g} and data.far={self.far:g} must enclose this scene's "
                                      f"depth bounds [{low:.3g}, {high:.3g}] (after scaling) when data.ndc=false; "
                                      f"e.g. data.near={0.9 * low:.3g} data.far={high:.3g}")
            self._data = data
        return self._data

    def split_rule(self) -> str:
        return holdout_rule(self.holdout)

    def views(self, split: str) -> Views:
        return self.load().split(split)

    def bounding_box(self) -> Tensor | None:
        """[2, 3] with ``ndc``: NDC's cube, x and y widened to +-1.5 for the rays of cameras beside the
        reference one, z in [-1, 1] (the near plane to infinity); without ``ndc`` None: bound from the cameras."""
        return torch.tensor([[-1.5, -1.5, -1.0], [1.5, 1.5, 1.0]]) if self.ndc else None

    def depth_bounds(self) -> Tensor:
        """[N, 2]: each image's near and far depth, scaled as the poses are."""
        return self.load().bounds

    def model_rays(self, origins: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        """World rays [..., 3] -> the rays the model renders: NDC rays with ``ndc``, else the same rays."""
        if not self.ndc:
            return origins, directions
        views = self.load().views
        return ndc_rays(origins, directions, views.intrinsics.params[0, 0].item(), views.height, views.width, NDC_NEAR)
