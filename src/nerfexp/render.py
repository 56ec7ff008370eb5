"""``nerfexp-render RUN_DIR``: a trained run's views along a camera path (``nerfexp.geometry.camera_paths``),
as videos and PNG frames.

What a render leaves in ``RUN_DIR/render/`` (the folder is replaced as a whole once every frame is
written, so a reader sees the previous render or the new one, never a part):
``rgb.mp4``, ``depth.mp4``, ``opacity.mp4``; the same frames as 8-bit PNGs ``rgb/0000.png``, ...,
``depth/0000.png``, ..., ``opacity/0000.png``, ...; and ``cameras.json``: the path's name, ``fps``,
``height``, ``width``, ``focal`` (pixels) and ``c2w`` per frame.
"""

import argparse
import contextlib
import json
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig
from torch import Tensor
from tqdm import tqdm

from nerfexp.arguments import add_run_arguments, command_parser, positive
from nerfexp.console import run_command
from nerfexp.data.base import Scene
from nerfexp.data.rays import model_batch
from nerfexp.extras import require
from nerfexp.files import atomic_directory
from nerfexp.geometry.camera_paths import llff_focus_depth, orbit_path, spiral_path
from nerfexp.geometry.cameras import camera_rays
from nerfexp.pixels import depth_image, png_bytes, to_uint8
from nerfexp.rundir import RENDER_DIR, find_run, load_module, run_config
from nerfexp.training.module import NeRFModule

PATHS = ("orbit", "spiral")
KINDS = ("rgb", "depth", "opacity")  # what is rendered of each frame, each a video and a folder of PNGs


def default_path(data: DictConfig) -> str:
    """``spiral`` for forward-facing scenes (the data config has ``ndc: true``, or builds an LLFF scene),
    else ``orbit``. Reads the keys defensively: a data config may have neither."""
    forward_facing = bool(data.get("ndc", False)) or "llff" in str(data.get("_target_", "")).lower()
    return "spiral" if forward_facing else "orbit"


def scene_focus_depth(scene: Scene) -> float:
    """The spiral's focus depth from the scene's depth bounds: its per-view ``depth_bounds()`` where it
    has them (LLFF), else its ray bounds ``ray_bounds()``."""
    bounds = scene.depth_bounds()
    near, far = scene.ray_bounds() if bounds is None else (bounds.min().item(), bounds.max().item())
    return llff_focus_depth(float(near), float(far))


def frame_size(height: int, width: int, focal: float, size: int | None) -> tuple[int, int, float]:
    """``(height, width, focal)`` of frames ``size`` pixels wide (None: the views' own width, made even),
    the height scaled by the same factor and rounded to an even number (video encoders need even sizes),
    the focal length (pixels) scaled with the width so the field of view stays the same."""
    size = size or max(2, width - width % 2)
    scaled_height = max(2, 2 * round(height * size / width / 2))
    return scaled_height, size, focal * size / width


def render_frame(module: NeRFModule, scene: Scene, c2w: Tensor, height: int, width: int,
                 focal: float) -> dict[str, Tensor]:
    """The module's render of camera ``c2w`` [4, 4]: ``rgb`` [H, W, 3], ``depth``, ``opacity`` [H, W].

    The camera's world rays become the model's rays as in training (``model_batch``); the module renders
    them ``module.chunk`` rays at a time, so memory is bounded at any resolution."""
    origins, directions = camera_rays(c2w.to(module.device, torch.float32), height, width, focal)
    batch = model_batch(scene, {"origins": origins, "directions": directions})
    return module.render_image(batch["origins"], batch["directions"], batch.get("viewdirs"))


def frame_images(frame: dict[str, Tensor], near: float, far: float) -> dict[str, Tensor]:
    """The images of a rendered frame, values in [0, 1]: ``rgb`` [H, W, 3]; ``depth`` (near white,
    far black, faded by opacity: ``nerfexp.pixels.depth_image``) and ``opacity`` [H, W]."""
    return {"rgb": frame["rgb"], "depth": depth_image(frame["depth"], frame["opacity"], near, far),
            "opacity": frame["opacity"]}


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
                writers[kind].append_data(frame if frame.ndim == 3 else np.repeat(frame[..., None], 3, -1))


def render_run(run: Path, overrides: list[str], n_frames: int, fps: float, size: int | None, chunk: int | None,
               path: str | None, focus: float | None) -> Path:
    """Render the run at ``run`` (a run directory, or a checkpoint file in one) along a camera path made
    from its training cameras: ``path`` (None: ``default_path``), into ``RUN_DIR/render``; returns it."""
    run_dir, checkpoint = find_run(run)
    cfg = run_config(run_dir, overrides)
    module, _ = load_module(cfg, checkpoint)
    if chunk is not None:
        module.chunk = chunk
    module.to("cuda" if torch.cuda.is_available() else "cpu").eval()
    scene = instantiate(cfg.data)
    views = scene.views("train")
    path = path or default_path(cfg.data)
    c2w = views.c2w.double()
    if path == "orbit":
        cameras = orbit_path(c2w, n_frames)
    else:
        cameras = spiral_path(c2w, n_frames, focus if focus is not None else scene_focus_depth(scene))
    height, width, focal = frame_size(views.height, views.width, views.focal, size)
    out_dir = run_dir / RENDER_DIR
    with atomic_directory(out_dir, replace=True) as new:
        render_path(module, scene, cameras, height, width, focal, new, fps)
        record = {"path": path, "fps": fps, "height": height, "width": width, "focal": focal,
                  "c2w": cameras.tolist()}
        (new / "cameras.json").write_text(json.dumps(record, indent=2))
    return out_dir


def _even(text: str) -> int:
    value = positive(int)(text)
    if value % 2:
        raise argparse.ArgumentTypeError(f"expected an even width (video encoders need one), got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    """``nerfexp-render RUN_DIR`` (or a checkpoint file in it): render the trained model along a camera
    path (an orbit around 360-degree scenes, a spiral for forward-facing ones) into RUN_DIR/render:
    rgb.mp4, depth.mp4, opacity.mp4 and their PNG frames."""
    parser = command_parser("nerfexp-render", build_parser.__doc__)
    add_run_arguments(parser)
    parser.add_argument("--path", choices=PATHS, help="camera path (default: spiral for forward-facing "
                        "scenes, i.e. data.ndc or an LLFF scene; else orbit)")
    parser.add_argument("--frames", type=positive(int), default=120, help="number of frames (default 120)")
    parser.add_argument("--fps", type=positive(float), default=30, help="frames per second of the videos (default 30)")
    parser.add_argument("--size", type=_even, help="frame width in pixels, even; the height keeps the "
                        "training views' aspect ratio (default: the training views' width)")
    parser.add_argument("--chunk", type=positive(int), help="rays rendered at once (default: the run's model.chunk)")
    parser.add_argument("--focus", type=positive(float), help="spiral only: the depth its cameras look at "
                        "(default: from the scene's depth bounds)")
    return parser


def main(argv: list[str] | None = None) -> None:
    """The ``nerfexp-render`` command (``build_parser``)."""
    def work(args: argparse.Namespace) -> str:
        require("imageio_ffmpeg", "nerfexp-render (its MP4 videos)")
        out_dir = render_run(args.run, args.overrides, args.frames, args.fps, args.size, args.chunk, args.path,
                             args.focus)
        return f"{args.frames} frames written to {out_dir}"
    run_command(build_parser(), argv, work)


if __name__ == "__main__":
    main()
