"""Camera path files: a render's ``cameras.json`` and a path saved by ``nerfexp-view``, the format
``nerfexp-render --cameras`` reads, checked key by key before anything is rendered."""

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from nerfexp.data.video import FPS_RANGE
from nerfexp.domains import TEXT, is_real, is_whole
from nerfexp.errors import NerfexpError
from nerfexp.geometry.cameras import poses_problem
from nerfexp.geometry.lens_records import FOCAL_RANGE, LensRecordError, lens_record, read_lens_record
from nerfexp.geometry.lenses import Intrinsics, inversion_problem
from nerfexp.memory import frame_bytes, require_memory
from nerfexp.reading import UnreadableFile, read_json

DEFAULT_FPS = 30.0  # of a camera path whose file names none, and of a path made from training cameras


@dataclass
class CameraPath:
    """The cameras of a video: ``c2w`` [F, 4, 4] float64 (OpenGL, ``nerfexp.geometry.cameras``), one per
    frame, seen through one lens ``intrinsics`` (shape []: ``nerfexp.geometry.lenses``) by frames ``height``
    x ``width`` pixels, played at ``fps``; ``name`` says where they came from (``orbit``, ``spiral``,
    ``viewer``, ...)."""

    name: str
    c2w: Tensor
    height: int
    width: int
    intrinsics: Intrinsics
    fps: float

    def record(self) -> dict:
        """The path as JSON data: keys path, fps, height, width, the lens (``lens_record``: camera_model,
        fl_x, fl_y, cx, cy and its coefficients) and c2w (a list of 4 x 4 lists)."""
        return {"path": self.name, "fps": self.fps, "height": self.height, "width": self.width,
                **lens_record(self.intrinsics), "c2w": self.c2w.tolist()}


def read_camera_path(file: Path) -> CameraPath:
    """The cameras of ``file`` (``CameraPath.record``'s JSON: a render's ``cameras.json``, a path saved by
    ``nerfexp-view``), checked: a NerfexpError naming the file, the key and what was expected where it is
    not JSON, lacks a key, has a size that is not positive and even (video encoders need even sizes), a lens
    that ``read_lens_record`` refuses (or, in a file of an earlier nerfexp, a ``focal`` outside
    ``FOCAL_RANGE``: a pinhole centred on the frame) or whose distortion cannot be inverted over the frame,
    an fps outside ``nerfexp.data.video.FPS_RANGE`` (what MP4 holds), or c2w
    is not a non-empty list of rigid 4 x 4 transforms placing the cameras within 2^24 scene units of the
    origin (``nerfexp.geometry.cameras.pose_problem``). ``path`` and ``fps`` may be left out (``file``, 30)."""
    try:
        data = read_json(Path(file))  # bounded: a file from others
    except UnreadableFile as error:
        raise NerfexpError(f"--cameras {file}: {error.reason}") from None
    expected = {"path": "a text (the path's name)", "height": "a positive even number of pixels",
                "width": "a positive even number of pixels",
                "fps": f"a number of frames per second in [{FPS_RANGE[0]:g}, {FPS_RANGE[1]:g}]",
                "c2w": "a non-empty list of 4 x 4 rigid camera-to-world matrices (OpenGL convention)"}
    ranges = {"focal": FOCAL_RANGE, "fps": FPS_RANGE}
    expected_focal = "a focal length in pixels in [2^-24, 2^24]"
    if not isinstance(data, dict):
        raise NerfexpError(f"--cameras {file}: expected a JSON object with keys {', '.join(expected)}")
    data = {"path": Path(file).name, "fps": DEFAULT_FPS, **data}
    for key, what in expected.items():
        if key not in data:
            raise NerfexpError(f"--cameras {file}: no key '{key}': expected {what}")
        value = data[key]
        if key == "c2w":
            problem = poses_problem(value)
        elif key == "path":
            problem = None if TEXT[1](value) else f"got {value!r:.80}"
        elif key in ("height", "width"):
            problem = None if is_whole(value) and value > 0 and value % 2 == 0 else f"got {value!r:.80}"
        elif not (is_real(value) and ranges[key][0] <= value <= ranges[key][1]):
            problem = f"got {value!r:.80}"
        else:
            problem = None
        if problem:
            raise NerfexpError(f"--cameras {file}: key '{key}': expected {what}, {problem}")
    height, width = data["height"], data["width"]
    if "focal" in data:  # a file of an earlier nerfexp: a pinhole centred on the frame
        if not (is_real(data["focal"]) and FOCAL_RANGE[0] <= data["focal"] <= FOCAL_RANGE[1]):
            raise NerfexpError(f"--cameras {file}: key 'focal': expected {expected_focal}, got {data['focal']!r:.80}")
        lens = Intrinsics.pinhole(float(data["focal"]), height, width)
    else:
        try:
            lens = read_lens_record(data)
        except LensRecordError as error:
            raise NerfexpError(f"--cameras {file}: key {error}") from None
        if problem := inversion_problem(lens, height, width):
            raise NerfexpError(f"--cameras {file}: the lens of {width} x {height} frames: {problem}")
    require_memory(f"--cameras {file}", f"a frame of {height} x {width} pixels", frame_bytes(height, width))
    return CameraPath(data["path"], torch.tensor(data["c2w"], dtype=torch.float64), height, width, lens,
                      float(data["fps"]))
