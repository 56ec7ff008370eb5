"""A trained model's frames: rendered band by band of rows (memory bounded at any size), as images, and
along a camera path into videos and PNG frames (``render_path``); the paths made from a scene's
training cameras (``training_path``)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import imageio.v2 as imageio
import numpy as np
import torch
from omegaconf import DictConfig
from torch import Tensor
from tqdm import tqdm

from nerfexp.data.base import Scene
from nerfexp.data.rays import model_batch
from nerfexp.errors import NerfexpError
from nerfexp.geometry.camera_paths import llff_focus_depth, orbit_path, spiral_path
from nerfexp.geometry.cameras import camera_rays
from nerfexp.geometry.lenses import Intrinsics
from nerfexp.pixels import depth_image, png_bytes, to_uint8
from nerfexp.products.camera_files import CameraPath

if TYPE_CHECKING:  # annotations only: it imports Lightning, which a command stopping at bad input need not wait for
    from nerfexp.training.module import NeRFModule

PATHS = ("orbit", "spiral")
KINDS = ("rgb", "depth", "opacity")  # what is rendered of each frame, each a video and a folder of PNGs


def default_path(data: DictConfig) -> str:
    """``spiral`` for forward-facing scenes (the data config has ``ndc: true``, or builds an LLFF scene),
    else ``orbit``. Reads the keys defensively: a data config may have neither."""
    forward_facing = bool(data.get("ndc", False)) or "llff" in str(data.get("_target_", "")).lower()
    return "spiral" if forward_facing else "orbit"


def scene_depth_range(scene: Scene) -> tuple[float, float]:
    """``(near, far)``: the depths the scene's content lies between, from its per-view ``depth_bounds()``
    where it has them (LLFF), else its ray bounds ``ray_bounds()``."""
    bounds = scene.depth_bounds()
    near, far = scene.ray_bounds() if bounds is None else (bounds.min().item(), bounds.max().item())
    return float(near), float(far)


def scene_focus_depth(scene: Scene) -> float:
    """The spiral's focus depth (``llff_focus_depth``) from the scene's depth range (``scene_depth_range``)."""
    return llff_focus_depth(*scene_depth_range(scene))


def frame_size(height: int, width: int, intrinsics: Intrinsics, size: int | None) -> tuple[int, int, Intrinsics]:
    """``(height, width, lens)`` of frames ``size`` pixels wide (None: the views' own width, made even) seen
    through the lens ``intrinsics`` (shape []) of ``height`` x ``width`` frames: the height scaled by the
    same factor and rounded to an even number (video encoders need even sizes), fx, fy and cx scaled with
    the width (square pixels stay square, the field of view the same) and cy with the height (a principal
    point at the centre stays there); the distortion is the lens's."""
    size = size or max(2, width - width % 2)
    scaled_height = max(2, 2 * round(height * size / width / 2))
    fx, fy, cx, cy = intrinsics.params.unbind(-1)
    params = torch.stack([fx * size / width, fy * size / width, cx * size / width, cy * scaled_height / height], -1)
    return scaled_height, size, Intrinsics(params, intrinsics.distortion, intrinsics.fisheye)


def frame_bands(module: NeRFModule, scene: Scene, c2w: Tensor, height: int, width: int,
                intrinsics: Intrinsics) -> Iterator[dict[str, Tensor]]:
    """The module's render of camera ``c2w`` [4, 4] with lens ``intrinsics`` (shape []) band by band of
    rows, top to bottom, each band's ``rgb`` [B, W, 3], ``depth``, ``opacity`` [B, W] rendered when it is
    asked for: a caller may stop between bands (the viewer abandons a render when its camera moves). A band
    is as many rows as ``module.chunk`` rays fill (at least one): one chunk, or the whole frame where it fits in one.

    The camera's world rays become the model's rays as in training (``model_batch``); the module renders
    them ``module.chunk`` rays at a time, so memory is bounded at any resolution."""
    origins, directions = camera_rays(c2w.to(module.device, torch.float32), height, width, intrinsics)
    batch = model_batch(scene, {"origins": origins, "directions": directions})
    rows = max(1, module.chunk // width)
    for start in range(0, height, rows):
        band = slice(start, start + rows)
        viewdirs = batch.get("viewdirs")
        yield module.render_image(batch["origins"][band], batch["directions"][band],
                                  None if viewdirs is None else viewdirs[band])


def render_frame(module: NeRFModule, scene: Scene, c2w: Tensor, height: int, width: int,
                 intrinsics: Intrinsics) -> dict[str, Tensor]:
    """The module's render of camera ``c2w`` [4, 4] with lens ``intrinsics`` (shape []): ``rgb`` [H, W, 3],
    ``depth``, ``opacity`` [H, W] (``frame_bands`` put together)."""
    bands = list(frame_bands(module, scene, c2w, height, width, intrinsics))
    return {key: torch.cat([band[key] for band in bands]) for key in bands[0]}


def frame_images(frame: dict[str, Tensor], near: float, far: float) -> dict[str, Tensor]:
    """The images of a rendered frame, values in [0, 1]: ``rgb`` [H, W, 3]; ``depth`` (near white,
    far black, faded by opacity: ``nerfexp.pixels.depth_image``) and ``opacity`` [H, W]."""
    return {"rgb": frame["rgb"], "depth": depth_image(frame["depth"], frame["opacity"], near, far),
            "opacity": frame["opacity"]}


def rgb_pixels(image: Tensor) -> np.ndarray:
    """8-bit RGB pixels [H, W, 3] of an image [H, W, 3] or a grey one [H, W] (its value in each channel)."""
    pixels = to_uint8(image)
    return pixels if pixels.ndim == 3 else np.repeat(pixels[..., None], 3, -1)


def render_path(module: NeRFModule, scene: Scene, cameras: Tensor, height: int, width: int,
                intrinsics: Intrinsics, out_dir: Path, fps: float) -> None:
    """Render ``cameras`` [F, 4, 4], seen through the lens ``intrinsics`` (shape []), frame by frame into
    ``out_dir``: a video per kind (``KINDS``) and the PNG frames, streamed to disk as they are rendered; with a
    progress bar. A video ffmpeg did not write is a NerfexpError (imageio's writer leaves ffmpeg's failure to its
    messages on stderr)."""
    near, far = module.renderer.near, module.renderer.ray_far
    with contextlib.ExitStack() as videos:
        writers = {kind: videos.enter_context(
            imageio.get_writer(out_dir / f"{kind}.mp4", format="FFMPEG", fps=fps, codec="libx264", quality=8,
                               macro_block_size=2)) for kind in KINDS}
        for index, c2w in enumerate(tqdm(cameras, desc="rendering", unit="frame", disable=None)):
            images = frame_images(render_frame(module, scene, c2w, height, width, intrinsics), near, far)
            for kind, image in images.items():
                frame = to_uint8(image)  # [H, W, 3] or [H, W]
                (out_dir / kind).mkdir(exist_ok=True)
                (out_dir / kind / f"{index:04d}.png").write_bytes(png_bytes(frame))
                writers[kind].append_data(rgb_pixels(image))
    unwritten = [video.name for kind in KINDS if not (video := out_dir / f"{kind}.mp4").is_file()
                 or video.stat().st_size == 0]
    if unwritten:
        raise NerfexpError(f"ffmpeg wrote no {', '.join(unwritten)} at {fps:g} frames per second (its messages "
                           "above say why)")


def training_path(scene: Scene, data: DictConfig, path: str | None, n_frames: int, focus: float | None,
                  fps: float) -> CameraPath:
    """A camera path of ``n_frames`` made from the scene's training cameras: ``path`` (``orbit_path`` or
    ``spiral_path`` looking at ``focus``, None: ``scene_focus_depth``; None: ``default_path`` of the data
    config), seen as the first training view is (its size and lens)."""
    views = scene.views("train")
    path = path or default_path(data)
    c2w = views.c2w.double()
    if path == "orbit":
        cameras = orbit_path(c2w, n_frames)
    else:
        cameras = spiral_path(c2w, n_frames, focus if focus is not None else scene_focus_depth(scene))
    return CameraPath(path, cameras, views.height, views.width, views.intrinsics[0], fps)
