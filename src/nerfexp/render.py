"""``nerfexp-render RUN_DIR``: a trained run's views along a camera path (``nerfexp.geometry.camera_paths``),
as videos and PNG frames.

What a render leaves in ``RUN_DIR/render/`` (the folder is replaced as a whole once every frame is
written, so a reader sees the previous render or the new one, never a part; a ``render/`` holding anything
else, ``MADE``, is refused with one line before any work):
``rgb.mp4``, ``depth.mp4``, ``opacity.mp4``; the same frames as 8-bit PNGs ``rgb/0000.png``, ...,
``depth/0000.png``, ..., ``opacity/0000.png``, ...; and ``cameras.json``: the path's name, ``fps``,
``height``, ``width``, ``focal`` (pixels) and ``c2w`` per frame.

``--cameras FILE`` renders the cameras of a file in that format instead of an orbit or a spiral: a
``cameras.json`` of an earlier render, or a path saved by ``nerfexp-view`` (``RUN_DIR/view/camera_path.json``).
"""

import argparse
import contextlib
import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig
from torch import Tensor
from tqdm import tqdm

from nerfexp.arguments import add_run_arguments, command_parser, fitting, positive
from nerfexp.console import run_command
from nerfexp.data.base import Scene
from nerfexp.data.rays import model_batch
from nerfexp.errors import NerfexpError
from nerfexp.extras import require
from nerfexp.files import TEMPORARY, atomic_directory, foreign_entries, foreign_message
from nerfexp.geometry.camera_paths import llff_focus_depth, orbit_path, spiral_path
from nerfexp.geometry.cameras import camera_rays, pose_problem
from nerfexp.memory import frame_bytes, require_memory
from nerfexp.pixels import depth_image, png_bytes, to_uint8
from nerfexp.rundir import RENDER_DIR, load_run
from nerfexp.training.module import NeRFModule

PATHS = ("orbit", "spiral")
KINDS = ("rgb", "depth", "opacity")  # what is rendered of each frame, each a video and a folder of PNGs
CAMERAS = "cameras.json"  # a render's cameras, in the format --cameras reads (``camera_path_record``)
MADE = (*(f"{kind}.mp4" for kind in KINDS), *(f"{kind}/*.png" for kind in KINDS), CAMERAS, *TEMPORARY)  # a render
DEFAULT_FPS = 30.0
DEFAULT_FRAMES = 120


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


def frame_size(height: int, width: int, focal: float, size: int | None) -> tuple[int, int, float]:
    """``(height, width, focal)`` of frames ``size`` pixels wide (None: the views' own width, made even),
    the height scaled by the same factor and rounded to an even number (video encoders need even sizes),
    the focal length (pixels) scaled with the width so the field of view stays the same."""
    size = size or max(2, width - width % 2)
    scaled_height = max(2, 2 * round(height * size / width / 2))
    return scaled_height, size, focal * size / width


def frame_bands(module: NeRFModule, scene: Scene, c2w: Tensor, height: int, width: int,
                focal: float) -> Iterator[dict[str, Tensor]]:
    """The module's render of camera ``c2w`` [4, 4] band by band of rows, top to bottom, each band's
    ``rgb`` [B, W, 3], ``depth``, ``opacity`` [B, W] rendered when it is asked for: a caller may stop
    between bands (the viewer abandons a render when its camera moves). A band is as many rows as
    ``module.chunk`` rays fill (at least one): one chunk, or the whole frame where it fits in one.

    The camera's world rays become the model's rays as in training (``model_batch``); the module renders
    them ``module.chunk`` rays at a time, so memory is bounded at any resolution."""
    origins, directions = camera_rays(c2w.to(module.device, torch.float32), height, width, focal)
    batch = model_batch(scene, {"origins": origins, "directions": directions})
    rows = max(1, module.chunk // width)
    for start in range(0, height, rows):
        band = slice(start, start + rows)
        viewdirs = batch.get("viewdirs")
        yield module.render_image(batch["origins"][band], batch["directions"][band],
                                  None if viewdirs is None else viewdirs[band])


def render_frame(module: NeRFModule, scene: Scene, c2w: Tensor, height: int, width: int,
                 focal: float) -> dict[str, Tensor]:
    """The module's render of camera ``c2w`` [4, 4]: ``rgb`` [H, W, 3], ``depth``, ``opacity`` [H, W]
    (``frame_bands`` put together)."""
    bands = list(frame_bands(module, scene, c2w, height, width, focal))
    return {key: torch.cat([band[key] for band in bands]) for key in bands[0]}


def frame_images(frame: dict[str, Tensor], near: float, far: float) -> dict[str, Tensor]:
    """The images of a rendered frame, values in [0, 1]: ``rgb`` [H, W, 3]; ``depth`` (near white,
    far black, faded by opacity: ``nerfexp.pixels.depth_image``) and ``opacity`` [H, W]."""
    return {"rgb": frame["rgb"], "depth": depth_image(frame["depth"], frame["opacity"], near, far),
            "opacity": frame["opacity"]}


@dataclass
class CameraPath:
    """The cameras of a video: ``c2w`` [F, 4, 4] float64 (OpenGL, ``nerfexp.geometry.cameras``), one per
    frame, seen by frames ``height`` x ``width`` pixels at ``focal`` (pixels), played at ``fps``; ``name``
    says where they came from (``orbit``, ``spiral``, ``viewer``, ...)."""

    name: str
    c2w: Tensor
    height: int
    width: int
    focal: float
    fps: float

    def record(self) -> dict:
        """The path as JSON data: keys path, fps, height, width, focal, c2w (a list of 4 x 4 lists)."""
        return {"path": self.name, "fps": self.fps, "height": self.height, "width": self.width,
                "focal": self.focal, "c2w": self.c2w.tolist()}


def _number(value, integer: bool = False) -> bool:
    """Whether a JSON value is a number (an integer where ``integer``), not a boolean."""
    return isinstance(value, int if integer else (int, float)) and not isinstance(value, bool)


def _c2w_problem(c2w) -> str | None:
    """Why a JSON value is not a non-empty list of rigid 4 x 4 camera-to-world matrices, or None."""
    if not isinstance(c2w, list):
        return f"got a {type(c2w).__name__}"
    if not c2w:
        return "got an empty list"
    for index, matrix in enumerate(c2w):
        shaped = isinstance(matrix, list) and len(matrix) == 4 and all(
            isinstance(row, list) and len(row) == 4 and all(map(_number, row)) for row in matrix)
        if not shaped:
            return f"item {index} is not a 4 x 4 matrix of numbers"
        if problem := pose_problem(torch.tensor(matrix, dtype=torch.float64)):
            return f"item {index} is not a rigid transform: {problem}"
    return None


def read_camera_path(file: Path) -> CameraPath:
    """The cameras of ``file`` (``CameraPath.record``'s JSON: a render's ``cameras.json``, a path saved by
    ``nerfexp-view``), checked: a NerfexpError naming the file, the key and what was expected where it is
    not JSON, lacks a key, has a size or focal length that is not positive (sizes also even: video encoders
    need them so), or c2w is not a non-empty list of rigid 4 x 4 transforms. ``path`` and ``fps`` may be
    left out (``file``, 30)."""
    try:
        data = json.loads(Path(file).read_text())
    except OSError as error:
        raise NerfexpError(f"--cameras {file}: cannot be read ({error.strerror})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise NerfexpError(f"--cameras {file}: not JSON ({error})") from None
    expected = {"height": "a positive even number of pixels", "width": "a positive even number of pixels",
                "focal": "a positive focal length in pixels", "fps": "a positive number of frames per second",
                "c2w": "a non-empty list of 4 x 4 rigid camera-to-world matrices (OpenGL convention)"}
    if not isinstance(data, dict):
        raise NerfexpError(f"--cameras {file}: expected a JSON object with keys {', '.join(expected)}")
    data = {"path": Path(file).name, "fps": DEFAULT_FPS, **data}
    for key, what in expected.items():
        if key not in data:
            raise NerfexpError(f"--cameras {file}: no key '{key}': expected {what}")
        value = data[key]
        if key == "c2w":
            problem = _c2w_problem(value)
        elif key in ("height", "width"):
            problem = None if _number(value, integer=True) and value > 0 and value % 2 == 0 else f"got {value!r}"
        elif not (_number(value) and 0 < value < float("inf")):
            problem = f"got {value!r}"
        else:
            problem = None
        if problem:
            raise NerfexpError(f"--cameras {file}: key '{key}': expected {what}, {problem}")
    require_memory(f"--cameras {file}", f"a frame of {data['height']} x {data['width']} pixels",
                   frame_bytes(data["height"], data["width"]))
    return CameraPath(str(data["path"]), torch.tensor(data["c2w"], dtype=torch.float64), data["height"],
                      data["width"], float(data["focal"]), float(data["fps"]))


def rgb_pixels(image: Tensor) -> np.ndarray:
    """8-bit RGB pixels [H, W, 3] of an image [H, W, 3] or a grey one [H, W] (its value in each channel)."""
    pixels = to_uint8(image)
    return pixels if pixels.ndim == 3 else np.repeat(pixels[..., None], 3, -1)


def render_path(module: NeRFModule, scene: Scene, cameras: Tensor, height: int, width: int, focal: float,
                out_dir: Path, fps: float) -> None:
    """Render ``cameras`` [F, 4, 4] frame by frame into ``out_dir``: a video per kind (``KINDS``) and
    the PNG frames, streamed to disk as they are rendered; with a progress bar."""
    near, far = module.renderer.near, module.renderer.far
    with contextlib.ExitStack() as videos:
        writers = {kind: videos.enter_context(
            imageio.get_writer(out_dir / f"{kind}.mp4", format="FFMPEG", fps=fps, codec="libx264", quality=8,
                               macro_block_size=2)) for kind in KINDS}
        for index, c2w in enumerate(tqdm(cameras, desc="rendering", unit="frame", disable=None)):
            images = frame_images(render_frame(module, scene, c2w, height, width, focal), near, far)
            for kind, image in images.items():
                frame = to_uint8(image)  # [H, W, 3] or [H, W]
                (out_dir / kind).mkdir(exist_ok=True)
                (out_dir / kind / f"{index:04d}.png").write_bytes(png_bytes(frame))
                writers[kind].append_data(rgb_pixels(image))


def training_path(scene: Scene, data: DictConfig, path: str | None, n_frames: int, focus: float | None,
                  fps: float) -> CameraPath:
    """A camera path of ``n_frames`` made from the scene's training cameras: ``path`` (``orbit_path`` or
    ``spiral_path`` looking at ``focus``, None: ``scene_focus_depth``; None: ``default_path`` of the data
    config), seen as the training views are (their size and focal length)."""
    views = scene.views("train")
    path = path or default_path(data)
    c2w = views.c2w.double()
    if path == "orbit":
        cameras = orbit_path(c2w, n_frames)
    else:
        cameras = spiral_path(c2w, n_frames, focus if focus is not None else scene_focus_depth(scene))
    return CameraPath(path, cameras, views.height, views.width, views.focal, fps)


def render_run(run: Path, overrides: list[str], n_frames: int, fps: float | None, size: int | None,
               chunk: int | None, path: str | None, focus: float | None,
               cameras: CameraPath | None = None) -> tuple[Path, int]:
    """Render the run at ``run`` (a run directory, or a checkpoint file in one) into ``RUN_DIR/render``
    along ``cameras`` (None: a ``training_path``), frames ``size`` pixels wide (``frame_size``; None: the
    cameras' own size) played at ``fps`` (None: the cameras'; 30 for a training path). Returns the folder
    and the number of frames."""
    run_dir, _, cfg, module, _ = load_run(run, overrides, chunk)
    out_dir = run_dir / RENDER_DIR
    if foreign := foreign_entries(out_dir, MADE):  # the folder is replaced as a whole: it must be a render
        raise NerfexpError(foreign_message(out_dir, foreign, "nerfexp-render", "move them elsewhere: "
                                           "nerfexp-render replaces this folder as a whole"))
    scene = instantiate(cfg.data)
    if cameras is None:
        cameras = training_path(scene, cfg.data, path, n_frames, focus, DEFAULT_FPS)
    height, width, focal = frame_size(cameras.height, cameras.width, cameras.focal, size)
    frames = CameraPath(cameras.name, cameras.c2w, height, width, focal, fps or cameras.fps)
    with atomic_directory(out_dir, replace=True) as new:
        render_path(module, scene, frames.c2w, height, width, focal, new, frames.fps)
        (new / CAMERAS).write_text(json.dumps(frames.record(), indent=2))
    return out_dir, len(frames.c2w)


def _even(text: str) -> int:
    value = fitting(positive(int), lambda width: frame_bytes(width, width), "a frame of N x N pixels")(text)
    if value % 2:
        raise argparse.ArgumentTypeError(f"expected an even width (video encoders need one), got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    """``nerfexp-render RUN_DIR`` (or a checkpoint file in it): render the trained model along a camera
    path (an orbit around 360-degree scenes, a spiral for forward-facing ones, or the cameras of a file)
    into RUN_DIR/render: rgb.mp4, depth.mp4, opacity.mp4, their PNG frames and cameras.json."""
    parser = command_parser("nerfexp-render", build_parser.__doc__)
    add_run_arguments(parser)
    parser.add_argument("--path", choices=PATHS, help="camera path (default: spiral for forward-facing "
                        "scenes, i.e. data.ndc or an LLFF scene; else orbit)")
    parser.add_argument("--cameras", type=Path, metavar="FILE",
                        help="render exactly the cameras of FILE instead of a path: a JSON object with keys "
                             "height, width, focal (pixels) and c2w (a list of 4 x 4 camera-to-world matrices, "
                             "OpenGL convention), optionally fps and path; e.g. a path saved by nerfexp-view "
                             "(RUN_DIR/view/camera_path.json) or an earlier render's cameras.json")
    parser.add_argument("--frames", type=positive(int), help=f"number of frames of the path (default {DEFAULT_FRAMES})")
    parser.add_argument("--fps", type=positive(float), help="frames per second of the videos (default: the "
                        "--cameras file's fps, else 30)")
    parser.add_argument("--size", type=_even, help="frame width in pixels, even; the height keeps the "
                        "cameras' aspect ratio (default: the training views' width, or the --cameras file's)")
    parser.add_argument("--chunk", type=positive(int), help="rays rendered at once (default: the run's model.chunk)")
    parser.add_argument("--focus", type=positive(float), help="spiral only: the depth its cameras look at "
                        "(default: from the scene's depth bounds)")
    return parser


def main(argv: list[str] | None = None) -> None:
    """The ``nerfexp-render`` command (``build_parser``)."""
    parser = build_parser()

    def work(args: argparse.Namespace) -> str:
        require("imageio_ffmpeg", "nerfexp-render (its MP4 videos)")
        cameras = None
        if args.cameras is not None:
            given = [flag for flag, value in (("--path", args.path), ("--frames", args.frames),
                                              ("--focus", args.focus)) if value is not None]
            if given:
                parser.error(f"--cameras renders the file's cameras: {', '.join(given)} do not apply")
            cameras = read_camera_path(args.cameras)  # checked before the run is loaded
        out_dir, n_frames = render_run(args.run, args.overrides, args.frames or DEFAULT_FRAMES, args.fps, args.size,
                                       args.chunk, args.path, args.focus, cameras)
        return f"{n_frames} frames written to {out_dir}"
    run_command(parser, argv, work)


if __name__ == "__main__":
    main()
