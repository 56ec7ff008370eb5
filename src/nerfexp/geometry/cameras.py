"""Camera poses, and the rays through a camera's pixels.

Convention (the NeRF / Blender / OpenGL one): a camera-to-world matrix ``c2w`` [4, 4] maps camera
coordinates to world coordinates; in camera coordinates x points right, y up, and the camera looks
down -z. Pixel (row i, column j) is sampled at its centre, (j + 0.5, i + 0.5) in image units, and seen
through the camera's lens (``nerfexp.geometry.lenses``: focal lengths, principal point, distortion).
Ray directions are unit vectors, so a ray parameter ``t`` is a distance in world units.
"""

import torch
from torch import Tensor

from nerfexp.domains import POSITION_LIMIT, Rule, is_position, list_of
from nerfexp.errors import DatasetError
from nerfexp.geometry.lenses import Intrinsics, pixel_grid, pixel_rays


def focal_from_fov(width: int, camera_angle_x: float) -> float:
    """Focal length in pixels of a camera whose horizontal field of view is ``camera_angle_x``."""
    return 0.5 * width / torch.tan(torch.tensor(0.5 * camera_angle_x, dtype=torch.float64)).item()


def camera_rays(c2w: Tensor, height: int, width: int, intrinsics: Intrinsics) -> tuple[Tensor, Tensor]:
    """World-space rays through every pixel centre of cameras ``c2w`` [..., 4, 4] with lenses ``intrinsics``
    (batch shape broadcastable to ``c2w``'s, e.g. [] for one lens; ``nerfexp.geometry.lenses``).

    Returns ``(origins, directions)``, each [..., H, W, 3] in ``c2w``'s dtype; directions have unit length.
    """
    lens = intrinsics.to(c2w.dtype, c2w.device).unsqueeze(2)  # [..., 1, 1]: broadcast over the pixels
    d_cam = pixel_rays(pixel_grid(height, width, dtype=c2w.dtype, device=c2w.device), lens)  # [..., H, W, 3]
    rotation = c2w[..., None, None, :3, :3]  # [..., 1, 1, 3, 3]
    directions = (rotation @ d_cam[..., None]).squeeze(-1)  # [..., H, W, 3]
    origins = c2w[..., None, None, :3, 3].expand_as(directions)
    return origins, directions


def look_at(eye: Tensor, target: Tensor, up: Tensor) -> Tensor:
    """Camera-to-world matrices [..., 4, 4] of cameras at ``eye`` [..., 3] looking at ``target``.

    ``up`` [3] is the world's up direction; it must not be parallel to the viewing direction.
    """
    back = eye - target  # the camera looks down -z, so +z points back from the target
    back = back / torch.linalg.vector_norm(back, dim=-1, keepdim=True)
    right = torch.linalg.cross(up.expand_as(back), back, dim=-1)
    right = right / torch.linalg.vector_norm(right, dim=-1, keepdim=True)
    cam_up = torch.linalg.cross(back, right, dim=-1)
    c2w = torch.zeros(*eye.shape[:-1], 4, 4, dtype=eye.dtype, device=eye.device)
    c2w[..., :3, 0], c2w[..., :3, 1], c2w[..., :3, 2], c2w[..., :3, 3] = right, cam_up, back, eye
    c2w[..., 3, 3] = 1
    return c2w


# a pose as a file lists it, for ``pose_problem`` to judge as float64: floats of any value (it names a NaN or a
# distance beyond 2^24), whole numbers within +-2^24 (no entry of a rigid pose lies beyond: a rotation's are
# within 1, a position's within 2^24; a larger whole number may have no float64)
POSE_LISTS: Rule = ("a 4x4 list of numbers (whole ones within +-2^24)",
                    list_of(list_of(("a number", lambda v: isinstance(v, float) or is_position(v)), 4), 4)[1])
RIGID_TOLERANCE = 1e-3  # how far a stored rotation may be from orthonormal (float32 poses are ~1e-7 off)


def rotation_problem(rotation: Tensor, tolerance: float = RIGID_TOLERANCE) -> str | None:
    """Why a matrix [3, 3] is not a rotation (orthonormal columns, determinant +1, within ``tolerance``
    elementwise of R^T R = I and of det R = 1), or None; a camera pose must be rigid."""
    rotation = rotation.double()
    if not torch.isfinite(rotation).all():
        return "its rotation is not finite"
    error = (rotation.T @ rotation - torch.eye(3, dtype=rotation.dtype)).abs().max()
    if error > tolerance:
        return f"its rotation is not orthonormal (R^T R differs from the identity by {float(error):.3g})"
    if torch.linalg.det(rotation) < 0:
        return "its rotation is a reflection (determinant -1)"
    return None


def pose_problem(c2w: Tensor, tolerance: float = RIGID_TOLERANCE) -> str | None:
    """Why a camera-to-world matrix [4, 4] is not a rigid transform (finite, a rotation by
    ``rotation_problem``, last row 0 0 0 1) placing the camera within ``POSITION_LIMIT`` of the origin
    along each axis, or None."""
    c2w = c2w.double()
    if not torch.isfinite(c2w).all():
        return "it is not finite"
    if c2w[:3, 3].abs().max() > POSITION_LIMIT:
        return (f"its position {c2w[:3, 3].tolist()} is more than 2^24 scene units from the origin, where float32 "
                "positions have no sub-unit resolution")
    if not torch.equal(c2w[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=c2w.dtype)):
        return f"its last row is {c2w[3].tolist()}, not [0, 0, 0, 1]"
    return rotation_problem(c2w[:3, :3], tolerance)


def poses_problem(c2w) -> str | None:
    """Why a JSON value is not a non-empty list of rigid 4 x 4 camera-to-world matrices (``POSE_LISTS``, then
    ``pose_problem``), in words naming the item, or None."""
    if not isinstance(c2w, list):
        return f"got a {type(c2w).__name__}"
    if not c2w:
        return "got an empty list"
    for index, matrix in enumerate(c2w):
        if not POSE_LISTS[1](matrix):
            return f"item {index} is not a 4 x 4 matrix of numbers (whole ones within +-2^24)"
        if problem := pose_problem(torch.tensor(matrix, dtype=torch.float64)):
            return f"item {index} is not a rigid camera pose: {problem}"
    return None


def centre_spread(centres: Tensor) -> float:
    """The spread of camera centres [N, 3] (N >= 1): their root mean square distance from their mean m,
    sqrt(mean_i |c_i - m|^2), in their units; 0 for one camera or cameras at one point. A similarity scales it
    as it scales distances. Example: centres (0, 0, 0) and (2, 0, 0): each 1 from m = (1, 0, 0), spread 1."""
    return torch.linalg.vector_norm(centres - centres.mean(0), dim=-1).square().mean().sqrt().item()


def normalize_centres(c2w: Tensor, points: Tensor, bound: float) -> tuple[Tensor, Tensor, Tensor, float]:
    """Centre on the mean camera centre m and scale by s = bound / max_i |c_i - m|, so that every camera lies
    within ``bound`` of the origin (a scene's orientation is kept).

    c2w [N, 4, 4], points [P, 3] -> (c2w with centres s (c - m), s (points - m), m [3], s).
    """
    centres = c2w[:, :3, 3]
    mean = centres.mean(0)
    radius = torch.linalg.vector_norm(centres - mean, dim=-1).max().item()
    if not radius > 0:
        raise DatasetError("all cameras are at one position: the scene's scale is undefined")
    scale = bound / radius
    normalized = c2w.clone()
    normalized[:, :3, 3] = (centres - mean) * scale
    return normalized, (points - mean) * scale, mean, scale
