"""The cameras of a browser viewer (viser, like OpenCV and COLMAP) as nerfexp's cameras, and back.

Conventions: nerfexp's camera-to-world matrices ``c2w`` [..., 4, 4] are OpenGL's (``nerfexp.geometry.cameras``:
x right, y up, looking down -z). A viewer's camera is OpenCV's: x right, y down, looking down +z, given
as an orientation ``wxyz`` [..., 4] (a unit quaternion w + xi + yj + zk, the rotation R in
p_world = R p_camera + t) and a ``position`` t [..., 3]; its field of view ``fov`` is vertical, in radians.
The two cameras at one pose share x and differ by the sign of y and z: c2w_opengl = c2w_opencv diag(1, -1, -1, 1).
"""

import math

import torch
from torch import Tensor

OPENCV_FROM_OPENGL = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))  # its own inverse


def quaternion_matrix(wxyz: Tensor) -> Tensor:
    """The rotations [..., 3, 3] of quaternions ``wxyz`` [..., 4] (normalized first).

    Example: (cos 45deg, 0, 0, sin 45deg), a quarter turn about z, maps x to y: [[0, -1, 0], [1, 0, 0], [0, 0, 1]].
    """
    w, x, y, z = (wxyz / torch.linalg.vector_norm(wxyz, dim=-1, keepdim=True)).unbind(-1)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return torch.stack([torch.stack(row, -1) for row in rows], -2)


def matrix_quaternion(rotation: Tensor) -> Tensor:
    """The unit quaternions ``wxyz`` [..., 4] (w >= 0) of rotations [..., 3, 3]: the inverse of
    ``quaternion_matrix`` up to the sign every quaternion shares with its negation.

    Each of 4 |w|, 4 |x|, 4 |y|, 4 |z| squared is 1 +- the diagonal's entries (e.g. 4 w^2 = 1 + trace);
    the quaternion is read off the row of the largest, whose divisor is then at least 2 (Shepperd's method).
    """
    m = rotation
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    squares = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22],
                          -1).clamp(min=0)  # [..., 4]: 4 w^2, 4 x^2, 4 y^2, 4 z^2 (they sum to 4)
    four = 2 * squares.sqrt()  # [..., 4]: 4 |w|, 4 |x|, 4 |y|, 4 |z|
    d21, d02, d10 = m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]
    s10, s02, s21 = m[..., 1, 0] + m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 2, 1] + m[..., 1, 2]
    candidates = torch.stack([  # [..., 4, 4]: row k is 4 q_k times the quaternion, e.g. row 0 (4 w^2, 4 wx, 4 wy, 4 wz)
        torch.stack([squares[..., 0], d21, d02, d10], -1),
        torch.stack([d21, squares[..., 1], s10, s02], -1),
        torch.stack([d02, s10, squares[..., 2], s21], -1),
        torch.stack([d10, s02, s21, squares[..., 3]], -1),
    ], -2) / four.clamp(min=1)[..., None]  # the largest of the four is at least 2: the chosen row's divisor
    best = four.argmax(-1)[..., None, None].expand(*four.shape[:-1], 1, 4)
    wxyz = candidates.gather(-2, best).squeeze(-2)
    wxyz = wxyz / torch.linalg.vector_norm(wxyz, dim=-1, keepdim=True)
    return torch.where(wxyz[..., :1] < 0, -wxyz, wxyz)


def viewer_c2w(wxyz: Tensor, position: Tensor) -> Tensor:
    """nerfexp's camera-to-world matrix [..., 4, 4] (OpenGL) of a viewer's camera (OpenCV): orientation
    ``wxyz`` [..., 4] and ``position`` [..., 3], as float64."""
    wxyz, position = wxyz.double(), position.double()
    c2w = torch.zeros(*position.shape[:-1], 4, 4, dtype=torch.float64)
    c2w[..., :3, :3] = quaternion_matrix(wxyz)
    c2w[..., :3, 3] = position
    c2w[..., 3, 3] = 1
    return c2w @ OPENCV_FROM_OPENGL


def viewer_pose(c2w: Tensor) -> tuple[Tensor, Tensor]:
    """A viewer's ``(wxyz [..., 4], position [..., 3])`` (OpenCV, float64) of nerfexp's cameras ``c2w``
    [..., 4, 4] (OpenGL): the inverse of ``viewer_c2w``."""
    opencv = c2w.double() @ OPENCV_FROM_OPENGL
    return matrix_quaternion(opencv[..., :3, :3]), opencv[..., :3, 3]


def vertical_fov(height: int, focal: float) -> float:
    """The vertical field of view (radians) of images ``height`` pixels tall at ``focal`` (pixels):
    2 atan(height / (2 focal)). Example: height 100, focal 50 gives 90 degrees. Its inverse is
    ``nerfexp.geometry.cameras.focal_from_fov(height, fov)`` (the same formula for either axis)."""
    return 2 * math.atan(0.5 * height / focal)

