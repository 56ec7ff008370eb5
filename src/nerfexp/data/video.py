"""Photographs for COLMAP taken from a video (``data.video``): the sharpest frame of each 1/fps seconds.

Names: ``rgb`` is a decoded frame, uint8 [H, W, 3]; ``grey`` its luma, float64 [H, W] in [0, 255];
``rate`` is the video's own frames per second, ``fps`` the frames per second kept (``data.fps``).

Frame k of the video (shown at k / rate seconds) falls in interval floor(k fps / rate), the interval i
spanning [i / fps, (i + 1) / fps) seconds. Of each interval's frames the one of greatest
``frame_sharpness`` (the variance of the Laplacian of its grey image) is kept, the first of equals: motion
blur and defocus flatten edges, and the Laplacian measures edges. A video of D seconds gives ceil(D fps)
frames (all of them where fps >= rate). Frames are decoded one at a time (imageio's FFMPEG plugin, the
``video`` extra): one interval's best frame is held, never the video.

The cache: the frames go to ``DIR/frames/`` (``000000.png``, ``000001.png``, ... numbered by interval,
so name order is time order, which COLMAP's sequential matcher follows) with ``source.json``, the
video's file name and the fps they were taken at. The folder is built under a temporary name and
renamed into place when complete (``nerfexp.files.atomic_directory``). A later run with the same video
name and fps reads the folder without decoding the video (which may then be gone); one with another
name or fps is refused, and nothing made earlier is overwritten or deleted.
"""

import json
import math
from collections.abc import Iterable, Iterator
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
from tqdm import tqdm

from nerfexp.domains import TEXT, real
from nerfexp.errors import ConfigError, DatasetError
from nerfexp.extras import require
from nerfexp.files import atomic_directory
from nerfexp.pixels import png_bytes
from nerfexp.reading import UnreadableFile, read_json

FRAMES = "frames"  # DIR/frames: the frames taken from the video
SOURCE = "source.json"  # DIR/frames/source.json: {"video": its file name, "fps": frames kept per second}
MIN_FRAMES = 3  # fewer frames than this cannot be posed usefully
# The frame rates of the videos nerfexp reads (data.fps) and writes (nerfexp-render): ffmpeg takes a rate as a
# fraction and MP4 counts each frame's duration in 32-bit ticks of a time base made from it, so rates far from
# 1 fail there (no video is written); from one frame per 1000 seconds to 1000 frames per second they hold, and
# faster is faster than displays show
FPS_RANGE = (1e-3, 1e3)
LUMA = (0.299, 0.587, 0.114)  # ITU-R BT.601 weights of R, G, B, as OpenCV's and Pillow's RGB -> grey
# what imageio's FFMPEG plugin raises for a file ffmpeg cannot read (its header parser: IndexError, AttributeError)
DECODE_ERRORS = (OSError, RuntimeError, ValueError, IndexError, AttributeError)


def luma(rgb: np.ndarray) -> np.ndarray:
    """The grey image [H, W] float64 of an 8-bit RGB frame [H, W, 3]: 0.299 R + 0.587 G + 0.114 B."""
    return rgb.astype(np.float64) @ np.array(LUMA)


def frame_sharpness(grey: np.ndarray) -> float:
    """The variance of the Laplacian of a grey image [H, W] (H, W >= 3) over its interior pixels:

        L[i, j] = g[i-1, j] + g[i+1, j] + g[i, j-1] + g[i, j+1] - 4 g[i, j],    sharpness = var(L)

    (the kernel [[0, 1, 0], [1, -4, 1], [0, 1, 0]]: OpenCV's ``cv2.Laplacian(g, cv2.CV_64F).var()``
    without the border pixels it reflects). Blur lowers it; a flat image has 0. Example: a single 1 in a
    5 x 5 image of zeros gives L = -4 there, 1 at its four neighbours and 0 at the other four interior
    pixels: mean 0, variance (16 + 4 x 1) / 9 = 20 / 9.
    """
    g = grey
    laplacian = g[:-2, 1:-1] + g[2:, 1:-1] + g[1:-1, :-2] + g[1:-1, 2:] - 4 * g[1:-1, 1:-1]  # [H-2, W-2]
    return float(laplacian.var())


def interval_of(frame_index: int, rate: float, fps: float) -> int:
    """The interval floor(k fps / rate) of frame k, which is shown at k / rate seconds; interval i spans
    [i / fps, (i + 1) / fps). Example: rate 30, fps 2: frames 0-14 in interval 0, 15-29 in 1."""
    return math.floor(frame_index * fps / rate)


def n_kept_of(n_frames: int, rate: float, fps: float) -> int:
    """How many frames ``sharpest_frames`` keeps of ``n_frames`` >= 0: one per interval they reach, which
    for fps <= rate is every interval up to the last frame's, interval_of(n_frames - 1) + 1, and for
    fps > rate is every frame. Example: 90 frames at rate 30 (3 s), fps 2: 6; 91 frames: 7."""
    return min(n_frames, interval_of(n_frames - 1, rate, fps) + 1) if n_frames > 0 else 0


def sharpest_frames(frames: Iterable[np.ndarray], rate: float, fps: float) -> Iterator[tuple[int, np.ndarray]]:
    """(interval, rgb) of the sharpest frame of each interval (``interval_of``) of ``frames``, a video's
    frames [H, W, 3] in order, the first of equally sharp ones; each yielded once its interval is over."""
    current, best, best_sharpness = -1, None, -math.inf
    for k, rgb in enumerate(frames):
        interval = interval_of(k, rate, fps)
        if interval != current:
            if best is not None:
                yield current, best
            current, best, best_sharpness = interval, None, -math.inf
        sharpness = frame_sharpness(luma(rgb))
        if sharpness > best_sharpness:
            best, best_sharpness = rgb, sharpness
    if best is not None:
        yield current, best


def frame_name(interval: int) -> str:
    """The file name of interval ``interval``'s frame: ``000012.png``; name order is time order."""
    return f"{interval:06d}.png"


def check_fps(fps) -> None:
    """A ConfigError unless ``fps`` (data.fps) is a number in ``FPS_RANGE``."""
    low, high = FPS_RANGE
    if isinstance(fps, bool) or not isinstance(fps, int | float) or not (math.isfinite(fps) and low <= fps <= high):
        raise ConfigError(f"data.fps must be a number in [{low:g}, {high:g}] (frames kept per second of video), "
                          f"got {fps}")


def cached_frames(folder: Path, video: str, fps: float) -> bool:
    """Whether ``folder`` holds the frames of ``video`` (compared by file name) at ``fps``: False where it
    does not exist; a DatasetError where it exists and holds anything else."""
    if not folder.exists():
        return False
    try:
        source = read_json(folder / SOURCE)  # bounded: the folder may come from elsewhere
        made_from = (source["video"], source["fps"])
        if not (TEXT[1](made_from[0]) and real(*FPS_RANGE)[1](made_from[1])):
            raise ValueError(made_from)
    except (UnreadableFile, ValueError, KeyError, TypeError):
        raise DatasetError(f"{folder} exists but holds no readable {SOURCE}, so nerfexp did not take it from a "
                           f"video; move it away (nerfexp never deletes it) to use data.video") from None
    if made_from != (Path(video).name, fps):
        raise DatasetError(f"{folder} holds the frames of {made_from[0]} at {made_from[1]:g} per second, not of "
                           f"{Path(video).name} at data.fps={fps:g}; move {FRAMES}/ and colmap/ away (nerfexp never "
                           f"deletes them) to take the frames again")
    return True


def last_line(error: Exception) -> str:
    """The last line of an error's message (ffmpeg's own complaint ends imageio's), or its type's name."""
    lines = str(error).strip().splitlines()
    return lines[-1].strip() if lines else type(error).__name__


def open_video(path: Path):
    """imageio's FFMPEG reader of the video ``path``, which streams its frames, and the video's (rate,
    duration in seconds, 0 where the file does not say). A DatasetError where ``path`` is missing or is
    not a video ffmpeg decodes."""
    require("imageio_ffmpeg", "data.video")
    if not path.is_file():
        raise DatasetError(f"video {path} does not exist (data.video, relative to data.root)")
    try:
        reader = imageio.get_reader(path, format="FFMPEG")
    except DECODE_ERRORS as error:
        raise DatasetError(f"{path}: not a video ffmpeg can decode (data.video): {last_line(error)}") from None
    meta = reader.get_meta_data()
    rate, duration = meta.get("fps", 0), meta.get("duration", 0)
    if not (isinstance(rate, int | float) and math.isfinite(rate) and rate > 0):
        reader.close()
        raise DatasetError(f"{path}: the video's frame rate is unknown (ffmpeg reads {rate!r}; data.video)")
    return reader, float(rate), float(duration or 0)


def decoded_frames(reader, path: Path) -> Iterator[np.ndarray]:
    """The frames [H, W, 3] uint8 of ``reader`` (``open_video``), decoded one at a time; a DatasetError
    naming ``path`` where decoding fails part way."""
    frames = iter(reader)
    while True:
        try:
            rgb = next(frames)
        except StopIteration:
            return
        except DECODE_ERRORS as error:
            raise DatasetError(f"{path}: decoding failed part way (data.video): {last_line(error)}") from None
        yield np.asarray(rgb)


def too_few(path: Path, n_frames: int, fps: float) -> DatasetError:
    """The error for a video that gives ``n_frames`` < MIN_FRAMES frames at ``fps``."""
    return DatasetError(f"{path} gives {n_frames} frames at data.fps={fps:g} (at least {MIN_FRAMES} needed): raise "
                        f"data.fps or use a longer video")


def video_frames(root, video: str, fps: float) -> Path:
    """The folder ``root/frames`` of the frames of ``video`` (relative to the scene folder ``root``, or
    absolute) at ``fps`` per second: the cached one, else made now with a progress bar over the decoded
    frames (see the module's docstring). Errors (fps <= 0, no folder ``root``, the video missing,
    undecodable or giving fewer than MIN_FRAMES frames by its duration) are raised before any frame is
    decoded; a video that turns out to give fewer, or fails to decode part way, leaves nothing behind."""
    check_fps(fps)
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root} is not a folder (data.root: the scene folder, where {FRAMES}/ and colmap/ are "
                           f"cached)")
    folder = root / FRAMES
    if cached_frames(folder, video, fps):
        return folder
    path = root / video
    reader, rate, duration = open_video(path)
    n_promised = round(duration * rate)  # the frames the file's duration promises (0 where it is unknown)
    with reader:
        if n_promised and n_kept_of(n_promised, rate, fps) < MIN_FRAMES:
            raise too_few(path, n_kept_of(n_promised, rate, fps), fps)
        progress = tqdm(decoded_frames(reader, path), total=n_promised or None, desc=f"frames of {path.name}",
                        unit="frame", disable=None)
        with atomic_directory(folder) as work, progress as frames:
            n_kept = 0
            for interval, rgb in sharpest_frames(frames, rate, fps):
                (work / frame_name(interval)).write_bytes(png_bytes(rgb))
                n_kept += 1
                frames.set_postfix_str(f"{n_kept} kept")
            if n_kept < MIN_FRAMES:
                raise too_few(path, n_kept, fps)
            (work / SOURCE).write_text(json.dumps({"video": Path(video).name, "fps": fps}) + "\n")
    return folder
