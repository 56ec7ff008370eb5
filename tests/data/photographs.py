"""Synthetic photographs with known cameras for the COLMAP and video tests: renders of the built-in scene
with textured backdrops from a ring of true cameras, and what compares recovered cameras with them (a
similarity by Umeyama's method, rotation angles)."""

import hashlib
import math

import numpy as np
import pycolmap
import torch
import torch.nn.functional as F
from PIL import Image

from nerfexp.data import procedural
from nerfexp.geometry.cameras import camera_rays, look_at
from nerfexp.geometry.lenses import Intrinsics

UP = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)


def umeyama(src: torch.Tensor, dst: torch.Tensor) -> tuple[float, torch.Tensor, torch.Tensor]:
    """The similarity (s, R [3, 3], t [3]) minimizing sum |dst - (s R src + t)|^2, src and dst [N, 3]
    (Umeyama 1991): with the centred points' covariance dst^T src / N = U D V^T and S = diag(1, 1,
    det(U V^T)), R = U S V^T, s = tr(D S) / var(src), t = mean(dst) - s R mean(src)."""
    src, dst = src.double(), dst.double()
    mu_src, mu_dst = src.mean(0), dst.mean(0)
    a, b = src - mu_src, dst - mu_dst
    U, D, Vt = torch.linalg.svd(b.T @ a / len(src))
    S = torch.ones(3, dtype=torch.float64)
    S[2] = torch.sign(torch.linalg.det(U @ Vt))
    R = U @ torch.diag(S) @ Vt
    s = (D * S).sum() / (a * a).sum(-1).mean()
    return s.item(), R, mu_dst - s * R @ mu_src


def rotation_degrees(R: torch.Tensor) -> torch.Tensor:
    """Rotation angles in degrees of rotation matrices [..., 3, 3]: acos((tr R - 1) / 2)."""
    cos = ((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)
    return torch.rad2deg(torch.acos(cos))


N_VIEWS, SIZE = 30, 384


FLOOR_Z, FLOOR_HALF, FLOOR_CELLS = -0.7, 2.0, 40  # a square floor under the slab (its bottom plane), 0.1 cells


DOME_RADIUS, DOME_CELLS = 8.0, 256  # a sphere around everything, seen from inside; 1.4 by 0.7 degree cells


def true_cameras() -> torch.Tensor:
    """c2w [30, 4, 4] float64 at radius 4 looking at the origin, 12 degrees apart in azimuth, on a
    wavy ring: elevation 30 + 8 sin(3 azimuth) degrees (camera centres not all in one plane)."""
    azimuth = 2 * math.pi * torch.arange(N_VIEWS, dtype=torch.float64) / N_VIEWS
    elevation = torch.deg2rad(30 + 8 * torch.sin(3 * azimuth))
    eye = procedural.CAMERA_RADIUS * torch.stack(
        [elevation.cos() * azimuth.cos(), elevation.cos() * azimuth.sin(), elevation.sin()], -1)
    return look_at(eye, torch.zeros(3, dtype=torch.float64), UP)


def texture(uv: torch.Tensor, cells: int, seed: int) -> torch.Tensor:
    """Colours [..., 3] at texture coordinates uv [..., 2] in [-1, 1]^2 of a random image of cells^2
    colours, bilinearly interpolated."""
    image = torch.rand(1, 3, cells, cells, generator=torch.Generator().manual_seed(seed), dtype=uv.dtype)
    colour = F.grid_sample(image, uv.reshape(1, -1, 1, 2), mode="bilinear", align_corners=False)  # [1, 3, M, 1]
    return colour[0, :, :, 0].T.reshape(*uv.shape[:-1], 3)


def render_photographs(c2w: torch.Tensor, focal: float) -> tuple[np.ndarray, torch.Tensor]:
    """8-bit RGB images [N, H, W, 3] and the true ray distances [N, H, W] of the built-in scene in a
    textured room: a floor and a dome of random colours behind it. The built-in scene alone has too
    few distinct features (smooth spheres, a repeating checker), and a floor alone is a plane, whose
    matches COLMAP (rightly) refuses to start a reconstruction from. The floor is the slab's bottom
    plane and the dome surrounds everything, so the scene occludes them by its alpha (2 x 2 rays per
    pixel: anti-aliased edges, which SIFT locates more precisely than one ray's staircase; at 256 px
    and one ray the centre error was 0.013-0.014, at the 1% limit), and the floor occludes the dome
    where it is hit. Distances are the scene's wherever any of a pixel's rays hits it. The camera is an
    ideal pinhole of focal length ``focal`` (pixels) centred on the image."""
    lens = Intrinsics.pinhole(focal, SIZE, SIZE)
    rgba = procedural.render_rgba(c2w, SIZE, SIZE, lens, supersample=2).double()  # [N, H, W, 4]
    origins, directions = camera_rays(c2w, SIZE, SIZE, lens)  # [N, H, W, 3]
    t_floor = (FLOOR_Z - origins[..., 2]) / directions[..., 2]
    floor_xy = (origins + t_floor[..., None] * directions)[..., :2]
    on_floor = (t_floor > 0) & (floor_xy.abs() < FLOOR_HALF).all(-1)
    b = (origins * directions).sum(-1)  # inside the dome: the far root of |o + t d| = R
    t_dome = -b + torch.sqrt(b * b - ((origins * origins).sum(-1) - DOME_RADIUS**2))
    x, y, z = (origins + t_dome[..., None] * directions).unbind(-1)
    dome_uv = torch.stack([torch.atan2(y, x) / math.pi, torch.asin(z / DOME_RADIUS) / (math.pi / 2)], -1)
    backdrop = torch.where(on_floor[..., None], texture(floor_xy / FLOOR_HALF, FLOOR_CELLS, 0),
                           texture(dome_uv, DOME_CELLS, 1))
    alpha = rgba[..., 3:]
    rgb = rgba[..., :3] * alpha + backdrop * (1 - alpha)
    t_scene, _, _ = procedural.intersect_scene(origins, directions)
    distance = torch.where(alpha[..., 0] > 0, t_scene, torch.where(on_floor, t_floor, t_dome))
    return (rgb * 255).round().to(torch.uint8).numpy(), distance


def digest(folder) -> dict[str, tuple[str, int]]:
    """Each file below ``folder``: its content hash and modification time (ns)."""
    return {p.relative_to(folder).as_posix(): (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
            for p in sorted(folder.rglob("*")) if p.is_file()}


WIDTH, HEIGHT, FOCAL = 8, 6, 10.0


def write_images(root, names, size=(WIDTH, HEIGHT)):
    (root / "images").mkdir(parents=True, exist_ok=True)
    for i, name in enumerate(names):
        Image.fromarray(np.full((size[1], size[0], 3), 10 * i % 256, dtype=np.uint8)).save(root / "images" / name)


# ---------------------------------------------------------------- a hand-made COLMAP model

RING = [(4.0, 0.0, 0.0), (0.0, 4.0, 0.0), (-4.0, 0.0, 0.0), (0.0, -4.0, 0.0)]  # cameras looking at the origin
POINTS = [(0.0, 0.0, 0.0), (0.0, 0.0, 1.0)]  # seen by every camera, at distances 4 and sqrt(17)
# near and far of RING and POINTS: each image sees distances {4, sqrt(17)}, and a percentile q of two values
# interpolates linearly, 4 + q (sqrt(17) - 4); near = 0.9 x the 0.1th, far = 1.1 x the 99.9th
RING_BOUNDS = (0.9 * (4 + 0.001 * (math.sqrt(17) - 4)), 1.1 * (4 + 0.999 * (math.sqrt(17) - 4)))


def colmap_pose(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> pycolmap.Rigid3d:
    """COLMAP's cam_from_world of a camera at ``eye`` looking at ``target``, written from COLMAP's own
    definition (x_cam = R x + t; rows of R: x right, y down, z forward), not from nerfexp's."""
    eye, target, up = (np.array(v, dtype=np.float64) for v in (eye, target, up))
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ eye)


def hand_made_model(principal_point=(WIDTH / 2, HEIGHT / 2), ring=RING, model="SIMPLE_PINHOLE",
                    distortion=()) -> pycolmap.Reconstruction:
    """Cameras on ``ring`` sharing one lens (COLMAP's ``model``: f, the principal point, then ``distortion``'s
    coefficients), and the two POINTS, each point observed by every camera where COLMAP projects it."""
    reconstruction = pycolmap.Reconstruction()
    reconstruction.add_camera_with_trivial_rig(pycolmap.Camera(
        model=model, width=WIDTH, height=HEIGHT, params=[FOCAL, *principal_point, *distortion], camera_id=1))
    camera = reconstruction.cameras[1]
    for i, eye in enumerate(ring, start=1):
        pose = colmap_pose(eye)
        keypoints = np.array([camera.img_from_cam(pose * np.array(p)) for p in POINTS])
        image = pycolmap.Image(name=f"view_{i}.png", keypoints=keypoints, camera_id=1, image_id=i)
        reconstruction.add_image_with_trivial_frame(image, pose)
    for k, point in enumerate(POINTS):
        track = pycolmap.Track([pycolmap.TrackElement(i, k) for i in range(1, len(ring) + 1)])
        reconstruction.add_point3D(np.array(point), track)
    return reconstruction
