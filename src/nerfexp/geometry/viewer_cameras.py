"""The cameras of a browser viewer (viser, like OpenCV and COLMAP) against nerfexp's cameras.

Conventions: nerfexp's camera-to-world matrices ``c2w`` [..., 4, 4] are OpenGL's (``nerfexp.geometry.cameras``:
x right, y up, looking down -z). A viewer's camera is OpenCV's: x right, y down, looking down +z; its field of
view ``fov`` is vertical, in radians. The two cameras at one pose share x and differ by the sign of y and z:
c2w_opengl = c2w_opencv diag(1, -1, -1, 1). (The viewer's orientations are quaternions, converted by viser's
own ``SO3``: ``nerfexp.products.viewer``.)
"""

import math

import torch
from torch import Tensor

OPENCV_FROM_OPENGL = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))  # its own inverse


def flip_camera_axes(c2w: Tensor) -> Tensor:
    """Camera-to-world matrices [..., 4, 4] of one convention as the other's, float64: OpenGL's as OpenCV's,
    or OpenCV's as OpenGL's (the flip of y and z is its own inverse)."""
    return c2w.double() @ OPENCV_FROM_OPENGL


def vertical_fov(height: int, focal: float) -> float:
    """The vertical field of view (radians) of images ``height`` pixels tall at ``focal`` (pixels):
    2 atan(height / (2 focal)). Example: height 100, focal 50 gives 90 degrees. Its inverse is
    ``nerfexp.geometry.cameras.focal_from_fov(height, fov)`` (the same formula for either axis)."""
    return 2 * math.atan(0.5 * height / focal)
