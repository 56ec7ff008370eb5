"""``nerfexp-render RUN_DIR``: a trained run's views along a camera path (``nerfexp.geometry.camera_paths``),
as videos and PNG frames.

What a render leaves in ``RUN_DIR/render/`` (the folder is replaced as a whole once every frame is
written, so a reader sees the previous render or the new one, never a part; a ``render/`` holding a file
that the run directory's manifest does not show to be nerfexp-render's, ``nerfexp.manifest``, is refused
with one line before any work, and checked again before it is replaced):
``rgb.mp4``, ``depth.mp4``, ``opacity.mp4``; the same frames as 8-bit PNGs ``rgb/0000.png``, ...,
``depth/0000.png``, ..., ``opacity/0000.png``, ...; and ``cameras.json``: the path's name, ``fps``,
``height``, ``width``, the lens (``camera_model``, ``fl_x``, ``fl_y``, ``cx``, ``cy`` in pixels and the
model's distortion coefficients: ``nerfexp.geometry.lens_records``) and ``c2w`` per frame.

``--cameras FILE`` renders the cameras of a file in that format instead of an orbit or a spiral: a
``cameras.json`` of an earlier render, or a path saved by ``nerfexp-view`` (``RUN_DIR/view/camera_path.json``).
"""

import argparse
import json
from pathlib import Path

from nerfexp.commands.arguments import (
    add_chunk_argument,
    add_run_arguments,
    command_parser,
    fitting,
    positive,
    say_unfinished,
    within,
)
from nerfexp.commands.console import run_command
from nerfexp.data.video import FPS_RANGE
from nerfexp.extras import require
from nerfexp.files import atomic_directory
from nerfexp.geometry.cameras import POSITION_LIMIT
from nerfexp.manifest import check_ours, folder_files, record_folder
from nerfexp.memory import frame_bytes, path_bytes
from nerfexp.products.camera_files import DEFAULT_FPS, CameraPath, read_camera_path
from nerfexp.products.frames import PATHS, frame_size, render_path, training_path
from nerfexp.products.trained import load_run, run_scene
from nerfexp.rundir.layout import RENDER_DIR

CAMERAS = "cameras.json"  # a render's cameras, in the format --cameras reads (``camera_path_record``)
DEFAULT_FRAMES = 120


def render_run(run: Path, overrides: list[str], n_frames: int, fps: float | None, size: int | None,
               chunk: int | None, path: str | None, focus: float | None,
               cameras: CameraPath | None = None) -> tuple[Path, int]:
    """Render the run at ``run`` (a run directory, or a checkpoint file in one) into ``RUN_DIR/render``
    along ``cameras`` (None: a ``training_path``), frames ``size`` pixels wide (``frame_size``; None: the
    cameras' own size) played at ``fps`` (None: the cameras'; 30 for a training path). Returns the folder
    and the number of frames."""
    run_dir, checkpoint, cfg, module, step = load_run(run, overrides, chunk)
    say_unfinished("nerfexp-render", run_dir, checkpoint, step)
    out_dir = run_dir / RENDER_DIR
    check_render_folder(run_dir)
    scene = run_scene(run_dir, cfg)  # its training cameras as refined, where the run refined them
    if cameras is None:
        cameras = training_path(scene, cfg.data, path, n_frames, focus, DEFAULT_FPS)
    height, width, lens = frame_size(cameras.height, cameras.width, cameras.intrinsics, size)
    frames = CameraPath(cameras.name, cameras.c2w, height, width, lens, fps or cameras.fps)
    with atomic_directory(out_dir, replace=True) as new:
        render_path(module, scene, frames.c2w, height, width, lens, new, frames.fps)
        (new / CAMERAS).write_text(json.dumps(frames.record(), indent=2))
        check_render_folder(run_dir)  # again: the render took a while
    record_folder(run_dir, RENDER_DIR)
    return out_dir, len(frames.c2w)


def check_render_folder(run_dir: Path) -> None:
    """A NerfexpError where ``RUN_DIR/render``, which a render replaces as a whole, holds a file that the run
    directory's manifest does not show to be a render's (``nerfexp.manifest.check_ours``)."""
    check_ours(run_dir, folder_files(run_dir, RENDER_DIR), "nerfexp-render",
               "move {it} elsewhere: nerfexp-render replaces this folder as a whole")


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
                             "height, width, the lens (fl_x, fl_y, cx, cy in pixels, optionally camera_model and "
                             "its coefficients, as nerfstudio names them; or one focal, a centred pinhole) and c2w "
                             "(a list of 4 x 4 camera-to-world matrices, OpenGL convention), optionally fps and "
                             "path; e.g. a path saved by nerfexp-view "
                             "(RUN_DIR/view/camera_path.json) or an earlier render's cameras.json")
    parser.add_argument("--frames", type=fitting(positive(int), path_bytes, "a camera path of N frames"),
                        help=f"number of frames of the path (default {DEFAULT_FRAMES})")
    parser.add_argument("--fps", type=within(*FPS_RANGE), help="frames per second of the videos, in "
                        f"[{FPS_RANGE[0]:g}, {FPS_RANGE[1]:g}] (MP4's range: nerfexp.data.video.FPS_RANGE; default: "
                        "the --cameras file's fps, else 30)")
    parser.add_argument("--size", type=_even, help="frame width in pixels, even; the height keeps the "
                        "cameras' aspect ratio (default: the training views' width, or the --cameras file's)")
    add_chunk_argument(parser)
    parser.add_argument("--focus", type=positive(float, POSITION_LIMIT), help="spiral only: the depth its cameras "
                        "look at, at most 2^24 scene units (default: from the scene's depth bounds)")
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
