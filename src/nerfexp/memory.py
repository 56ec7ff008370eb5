"""Memory estimates that refuse a size before any work: a scene, the networks' working arrays, a grid or a
frame that would not fit in this machine's memory is one line naming the setting and the estimate.

The estimates are deliberately simple lower bounds: the arrays that must exist at once (a training step
keeps every layer's output for its backward pass; an evaluation holds one layer's at a time), so that a
size they refuse cannot fit, while one they pass may still be too large or slow.
"""

import os

from nerfexp.errors import ConfigError
from nerfexp.sizes import FLOAT

PIXEL_BYTES = 9 * FLOAT  # a scene's pixel (a traced ray while it is made): its origin, direction and colour
SAMPLE_BYTES = 8 * FLOAT  # a ray sample's position, direction, density and colour, before the networks
FRAME_PIXEL_BYTES = 5 * FLOAT  # a rendered frame's colour, depth and opacity
CAMERA_BYTES = 16 * 2 * FLOAT  # a camera path's frame: its 4 x 4 float64 camera-to-world matrix


def machine_bytes() -> int:
    """This machine's total physical memory in bytes."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


UNITS = ("bytes", "KiB", "MiB", "GiB", "TiB", "PiB", "EiB")


def readable(n_bytes: int) -> str:
    """``n_bytes`` (a whole number) in the largest binary unit that keeps it at least 1 (``1.5 GiB``); past
    1024 EiB as a power of two (``2^90 bytes``): an estimate of any size is said without a float overflowing."""
    n_bytes = int(n_bytes)
    power = (n_bytes.bit_length() - 1) // 10 if n_bytes > 0 else 0  # 1024^power <= n_bytes < 1024^(power + 1)
    if power >= len(UNITS):
        return f"2^{n_bytes.bit_length() - 1} bytes"
    return f"{n_bytes / 1024 ** power:.3g} {UNITS[power]}" if power else f"{n_bytes} bytes"


def require_memory(setting: str, what: str, n_bytes: int, available: int | None = None) -> None:
    """A ConfigError naming ``setting`` (``scale.image_size=100000``) where ``what`` needs an estimated
    ``n_bytes``, more than ``available`` (default: the machine's memory)."""
    available = machine_bytes() if available is None else available
    if n_bytes > available:
        raise ConfigError(f"{setting}: {what} needs about {readable(n_bytes)} of memory, more than this machine's "
                          f"{readable(available)}")


def scene_bytes(n_images: int, height: int, width: int, supersample: int = 1) -> int:
    """A scene held in memory: ``n_images`` views of ``height`` x ``width`` pixels, each traced with
    ``supersample``^2 rays while it is made."""
    return n_images * height * width * supersample ** 2 * PIXEL_BYTES


def network_bytes(rays: int, samples: int, width: int, depth: int, training: bool = True) -> int:
    """The working arrays of ``rays`` rays of ``samples`` samples each through a network of ``depth``
    hidden layers of ``width`` units: in ``training`` every layer's output, kept for the backward pass;
    in an evaluation one layer's."""
    points = rays * samples
    return points * (SAMPLE_BYTES + (depth if training else 1) * width * FLOAT)


def path_bytes(n_frames: int) -> int:
    """A camera path of ``n_frames`` cameras (nerfexp-render's ``--frames``)."""
    return n_frames * CAMERA_BYTES


def frame_bytes(height: int, width: int) -> int:
    """One rendered frame of ``height`` x ``width`` pixels: its colour, depth and opacity."""
    return height * width * FRAME_PIXEL_BYTES
