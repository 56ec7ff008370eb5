"""Camera lenses: focal lengths, principal point and lens distortion, and the ray direction through a pixel.

Conventions (COLMAP's, OpenCV's and nerfstudio's). A pixel (row i, column j) is sampled at its centre,
image coordinates ``(u, v) = (j + 0.5, i + 0.5)``, u to the right and v down. A lens maps them to the
*distorted normalized* coordinates ``p_d = ((u - cx) / fx, (v - cy) / fy)``, and the distortion maps the
*normalized* coordinates ``p = (x / z, y / z)`` of a camera-space point (x right, y down, z forward)
to ``p_d``:

    perspective (OpenCV's full model; PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV are special
    cases), with s = |p|^2 = x^2 + y^2 and the radial factor R(s) = P(s) / Q(s),
        P(s) = 1 + k1 s + k2 s^2 + k3 s^3,  Q(s) = 1 + k4 s + k5 s^2 + k6 s^3,
        x_d = x R + 2 p1 x y + p2 (s + 2 x^2),   y_d = y R + p1 (s + 2 y^2) + 2 p2 x y;
    fisheye (OPENCV_FISHEYE, RADIAL_FISHEYE, SIMPLE_RADIAL_FISHEYE), with theta the angle from the axis,
        theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8),  p_d = theta_d p / |p|.

A ray's direction is found by inverting the distortion (``undistort``: Newton's method from p = p_d, a
fixed number of steps) and is returned in nerfexp's camera convention (``nerfexp.geometry.cameras``:
x right, y up, looking down -z), unit length. A fisheye's direction is built from theta itself,
(sin theta p_d / |p_d|, cos theta), so a lens wider than 180 degrees has no infinite coordinate.
``inversion_problem`` says, before any ray is made, whether a lens's distortion can be inverted over
its whole image (the radial map increasing out to the image's edge, Newton's steps converged).

``distortion`` is always ``[..., 8]``: ``(k1, k2, k3, k4, k5, k6, p1, p2)`` for a perspective lens and
``(k1, k2, k3, k4, 0, 0, 0, 0)`` for a fisheye one (``PARAMETERS`` names them per COLMAP model).
"""

import math
from dataclasses import dataclass

import torch
from torch import Tensor

UNDISTORT_STEPS = 20  # Newton steps; converged (checked by ``inversion_problem``) within a handful for real lenses
ROUND_TRIP_PIXELS = 1e-3  # how far distort(undistort(p)) may land from p, in pixels, for a lens to be invertible
RADIAL_SAMPLES = 4096  # angles from the axis at which the radial map is checked to be increasing
BORDER_SAMPLES = 129  # points per image side (the corners included) at which the inversion is checked
# COLMAP's parameter names after fx, fy, cx, cy (or f, cx, cy), per model nerfexp reads, and whether it is a fisheye
PARAMETERS = {
    "SIMPLE_PINHOLE": (), "PINHOLE": (), "SIMPLE_RADIAL": ("k1",), "RADIAL": ("k1", "k2"),
    "OPENCV": ("k1", "k2", "p1", "p2"), "FULL_OPENCV": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "SIMPLE_RADIAL_FISHEYE": ("k1",), "RADIAL_FISHEYE": ("k1", "k2"), "OPENCV_FISHEYE": ("k1", "k2", "k3", "k4"),
}
FISHEYE_MODELS = ("SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "OPENCV_FISHEYE")
SLOTS = ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2")  # the layout of ``distortion``'s last axis


def distortion_vector(named: dict[str, float], dtype=torch.float64) -> Tensor:
    """The ``[8]`` distortion (``SLOTS``) of named coefficients such as ``{"k1": 0.1, "p2": 0.01}``; the
    others are 0."""
    return torch.tensor([float(named.get(name, 0.0)) for name in SLOTS], dtype=dtype)


@dataclass(frozen=True)
class Intrinsics:
    """The lenses of a batch of cameras, every tensor with the same leading shape ``[...]`` (``[N]`` for N
    views, ``[]`` for one camera).

    params: [..., 4] ``(fx, fy, cx, cy)`` in pixels (image coordinates: module docstring).
    distortion: [..., 8] the coefficients ``SLOTS`` (zero: no distortion).
    fisheye: [...] bool, whether ``distortion`` is a fisheye's.
    """

    params: Tensor
    distortion: Tensor
    fisheye: Tensor

    @classmethod
    def pinhole(cls, focal: float, height: int, width: int, shape: tuple[int, ...] = (),
                dtype=torch.float64) -> "Intrinsics":
        """Ideal pinholes of focal length ``focal`` (pixels) with the principal point at the image centre."""
        params = torch.tensor([focal, focal, 0.5 * width, 0.5 * height], dtype=dtype).expand(*shape, 4).clone()
        return cls(params, torch.zeros(*shape, len(SLOTS), dtype=dtype), torch.zeros(shape, dtype=torch.bool))

    @classmethod
    def stack(cls, lenses: list["Intrinsics"]) -> "Intrinsics":
        """One batch [N] of N single lenses (each of shape [])."""
        return cls(torch.stack([lens.params for lens in lenses]), torch.stack([lens.distortion for lens in lenses]),
                   torch.stack([lens.fisheye for lens in lenses]))

    @property
    def shape(self) -> torch.Size:
        return self.fisheye.shape

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, index) -> "Intrinsics":
        return Intrinsics(self.params[index], self.distortion[index], self.fisheye[index])

    def to(self, dtype: torch.dtype | None = None, device=None) -> "Intrinsics":
        """The same lenses with ``params`` and ``distortion`` in ``dtype`` on ``device``."""
        return Intrinsics(self.params.to(device, dtype), self.distortion.to(device, dtype), self.fisheye.to(device))

    def unsqueeze(self, n: int) -> "Intrinsics":
        """The lenses with ``n`` more batch axes of size 1 after the existing ones (to broadcast over pixels)."""
        index = (..., *(None,) * n)
        return Intrinsics(self.params[(*index, slice(None))], self.distortion[(*index, slice(None))],
                          self.fisheye[index])

    def resized(self, old_size: tuple[int, int], new_size: tuple[int, int]) -> "Intrinsics":
        """The lenses of the images ``old_size`` = (H, W) resampled to ``new_size`` (H', W') over the same
        extent (area averaging, a render's frame size): fx, cx scaled by W' / W, fy, cy by H' / H."""
        (height, width), (new_height, new_width) = old_size, new_size
        like = {"dtype": self.params.dtype, "device": self.params.device}
        old = torch.tensor([width, height, width, height], **like)
        new = torch.tensor([new_width, new_height, new_width, new_height], **like)
        return Intrinsics(self.params * new / old, self.distortion, self.fisheye)  # (p W') / W: exact for centres

    def is_distorted(self) -> Tensor:
        """[...] bool: whether a lens is not an ideal pinhole (a fisheye, or any coefficient nonzero)."""
        return self.fisheye | (self.distortion != 0).any(-1)


def _radial(distortion: Tensor, s: Tensor) -> tuple[Tensor, Tensor]:
    """R(s) = P(s) / Q(s) and dR/ds of a perspective lens (module docstring), s = x^2 + y^2 [...]."""
    k1, k2, k3, k4, k5, k6 = distortion[..., :6].unbind(-1)
    P, dP = 1 + s * (k1 + s * (k2 + s * k3)), k1 + s * (2 * k2 + 3 * s * k3)
    Q, dQ = 1 + s * (k4 + s * (k5 + s * k6)), k4 + s * (2 * k5 + 3 * s * k6)
    return P / Q, (dP * Q - P * dQ) / Q.square()


def _fisheye_angle(distortion: Tensor, theta: Tensor) -> tuple[Tensor, Tensor]:
    """theta_d(theta) and its derivative for a fisheye lens (module docstring)."""
    k1, k2, k3, k4 = distortion[..., :4].unbind(-1)
    t2 = theta.square()
    theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    slope = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
    return theta_d, slope


def _perspective(p: Tensor, distortion: Tensor) -> tuple[Tensor, Tensor]:
    """The distorted coordinates [..., 2] of normalized ones ``p`` [..., 2], and the Jacobian [..., 2, 2]."""
    x, y = p.unbind(-1)
    p1, p2 = distortion[..., 6], distortion[..., 7]
    s = x * x + y * y
    R, dR = _radial(distortion, s)
    x_d = x * R + 2 * p1 * x * y + p2 * (s + 2 * x * x)
    y_d = y * R + p1 * (s + 2 * y * y) + 2 * p2 * x * y
    cross = 2 * x * y * dR + 2 * p1 * x + 2 * p2 * y
    jacobian = torch.stack([torch.stack([R + 2 * x * x * dR + 2 * p1 * y + 6 * p2 * x, cross], -1),
                            torch.stack([cross, R + 2 * y * y * dR + 6 * p1 * y + 2 * p2 * x], -1)], -2)
    return torch.stack([x_d, y_d], -1), jacobian


def distort(p: Tensor, distortion: Tensor, fisheye: Tensor) -> Tensor:
    """Distorted normalized coordinates [..., 2] of normalized coordinates ``p`` [..., 2] (module
    docstring); ``distortion`` [..., 8] and ``fisheye`` [...] broadcast against ``p``'s leading axes."""
    perspective, _ = _perspective(p, distortion)
    r = torch.linalg.vector_norm(p, dim=-1)
    theta_d, _ = _fisheye_angle(distortion, torch.atan(r))
    ratio = torch.where(r > 0, theta_d / torch.where(r > 0, r, 1), 1)  # theta_d / r -> 1 as r -> 0
    return torch.where(fisheye[..., None], p * ratio[..., None], perspective)


def undistort_perspective(p_d: Tensor, distortion: Tensor, steps: int = UNDISTORT_STEPS) -> Tensor:
    """Normalized coordinates p [..., 2] with ``distort(p) = p_d`` for a perspective lens: Newton's method
    from p = p_d, ``steps`` steps with the 2 x 2 Jacobian inverted in closed form (a singular Jacobian
    leaves the point where it is; ``inversion_problem`` refuses lenses where that happens)."""
    p = p_d
    for _ in range(steps):
        value, J = _perspective(p, distortion)
        residual = value - p_d
        det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
        safe = torch.where(det != 0, det, 1)
        dx = (J[..., 1, 1] * residual[..., 0] - J[..., 0, 1] * residual[..., 1]) / safe
        dy = (J[..., 0, 0] * residual[..., 1] - J[..., 1, 0] * residual[..., 0]) / safe
        p = p - torch.where((det != 0)[..., None], torch.stack([dx, dy], -1), 0)
    return p


def undistort_angle(theta_d: Tensor, distortion: Tensor, steps: int = UNDISTORT_STEPS) -> Tensor:
    """The angle theta [...] from the axis with ``theta_d(theta) = theta_d`` for a fisheye lens: Newton's
    method from theta = theta_d (a zero slope leaves it where it is; ``inversion_problem`` refuses such lenses)."""
    theta = theta_d
    for _ in range(steps):
        value, slope = _fisheye_angle(distortion, theta)
        theta = theta - torch.where(slope != 0, (value - theta_d) / torch.where(slope != 0, slope, 1), 0)
    return theta


def normalized_coordinates(pixels: Tensor, intrinsics: Intrinsics) -> Tensor:
    """Distorted normalized coordinates [..., 2] of image coordinates ``pixels`` [..., 2] (u, v)."""
    fx, fy, cx, cy = intrinsics.params.unbind(-1)
    return torch.stack([(pixels[..., 0] - cx) / fx, (pixels[..., 1] - cy) / fy], -1)


def pinhole_directions(p: Tensor) -> Tensor:
    """Unit ray directions [..., 3] in nerfexp's camera convention (x right, y up, looking down -z) through
    undistorted normalized coordinates ``p`` [..., 2] (x, y): (x, -y, -1) / |(x, -y, -1)|."""
    x, y = p.unbind(-1)
    d = torch.stack([x, -y, -torch.ones_like(x)], -1)
    return d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)


def fisheye_directions(p_d: Tensor, distortion: Tensor) -> Tensor:
    """Unit ray directions [..., 3] in nerfexp's camera convention through a fisheye's distorted normalized
    coordinates ``p_d`` [..., 2] (``distortion`` [..., 8] broadcast against them): the angle theta from the axis
    undistorted from theta_d = |p_d| (``undistort_angle``), the direction (sin theta p_d / |p_d|, cos theta)."""
    theta_d = torch.linalg.vector_norm(p_d, dim=-1)
    theta = undistort_angle(theta_d, distortion)
    sideways = torch.where(theta_d > 0, torch.sin(theta) / torch.where(theta_d > 0, theta_d, 1), 1)  # -> 1 at 0
    return torch.stack([sideways * p_d[..., 0], -sideways * p_d[..., 1], -torch.cos(theta)], -1)


def pixel_rays(pixels: Tensor, intrinsics: Intrinsics) -> Tensor:
    """Unit ray directions [..., 3] in nerfexp's camera convention (x right, y up, looking down -z) through
    image coordinates ``pixels`` [..., 2] (u, v) of cameras ``intrinsics`` (broadcast against ``pixels``'s
    leading axes). An ideal pinhole's direction is (x, -y, -1) / |(x, -y, -1)| with
    (x, y) = ((u - cx) / fx, (v - cy) / fy); distorted lenses are undistorted first (module docstring), each
    pixel by its own lens's solve alone: Newton's in p for a distorted perspective lens, in theta for a fisheye,
    none for a pinhole (whose solve would leave p where it is)."""
    p_d = normalized_coordinates(pixels, intrinsics)  # [..., 2]
    distorted = intrinsics.is_distorted()
    if not distorted.any():  # every lens an ideal pinhole: nothing to invert
        return pinhole_directions(p_d)
    shape = p_d.shape[:-1]  # the pixels' and the lenses' leading axes broadcast
    distortion = intrinsics.distortion.expand(*shape, len(SLOTS))
    p_d = p_d.to(torch.promote_types(p_d.dtype, distortion.dtype))
    perspective = (distorted & ~intrinsics.fisheye).expand(shape)  # pixels of a distorted perspective lens
    fisheye = intrinsics.fisheye.expand(shape)
    p = p_d.clone()
    p[perspective] = undistort_perspective(p_d[perspective], distortion[perspective])
    rays = pinhole_directions(p)
    rays[fisheye] = fisheye_directions(p_d[fisheye], distortion[fisheye])
    return rays


def pixel_grid(height: int, width: int, dtype=torch.float32, device=None) -> Tensor:
    """Image coordinates [H, W, 2] (u, v) of every pixel centre: (j + 0.5, i + 0.5)."""
    rows = torch.arange(height, dtype=dtype, device=device) + 0.5
    cols = torch.arange(width, dtype=dtype, device=device) + 0.5
    v, u = torch.meshgrid(rows, cols, indexing="ij")
    return torch.stack([u, v], -1)


def corner_pixels(height: int, width: int) -> Tensor:
    """Image coordinates [4, 2] float64 of an image's four corner pixels' centres: (0.5, 0.5), (W - 0.5, 0.5),
    (0.5, H - 0.5), (W - 0.5, H - 0.5)."""
    return torch.tensor([[0.5, 0.5], [width - 0.5, 0.5], [0.5, height - 0.5], [width - 0.5, height - 0.5]],
                        dtype=torch.float64)


def border_pixels(height: int, width: int, samples: int = BORDER_SAMPLES) -> Tensor:
    """Image coordinates [K, 2] float64 covering an image's whole extent, its corners (0, 0) and (W, H)
    included: a ``samples`` x ``samples`` grid."""
    u = torch.linspace(0, width, samples, dtype=torch.float64)
    v = torch.linspace(0, height, samples, dtype=torch.float64)
    return torch.stack(torch.meshgrid(u, v, indexing="xy"), -1).reshape(-1, 2)


def radial_reach(distortion: Tensor, fisheye: bool) -> tuple[float, float]:
    """How far out a lens's radial map (r R(r^2) of the normalized radius r for a perspective lens,
    theta_d(theta) of the angle theta for a fisheye) increases: ``(where, reach)``, the radius or angle where
    it first stops increasing and the distorted radius it reaches there (``inf, inf`` for a perspective lens
    that increases over every angle below 90 degrees; a fisheye is followed up to 180 degrees). Sampled at
    ``RADIAL_SAMPLES`` angles, evenly from the axis out."""
    angles = torch.linspace(0, torch.pi / 2 if not fisheye else torch.pi, RADIAL_SAMPLES + 1, dtype=torch.float64)
    if fisheye:
        radii = angles
        value, slope = _fisheye_angle(distortion, radii)
    else:
        radii = torch.tan(angles[:-1])  # up to 90 degrees, not at it
        R, dR = _radial(distortion, radii.square())
        value, slope = radii * R, R + 2 * radii.square() * dR  # d(r R(r^2)) / dr
    stops = ~(torch.isfinite(slope) & (slope > 0))
    if not stops.any():
        return (float(radii[-1]), float(value[-1])) if fisheye else (math.inf, math.inf)
    first = int(stops.nonzero()[0])
    return float(radii[first]), float(value[:first + 1].max()) if first else 0.0


def inversion_problem(intrinsics: Intrinsics, height: int, width: int) -> str | None:
    """Why the distortion of one lens (``intrinsics`` of shape []) cannot be inverted over an image of
    ``height`` x ``width`` pixels, or None: checked in float64 on a grid over the image's extent, corners
    included (``border_pixels``), the radial map must increase from the axis out past the image's farthest
    point (``radial_reach``; a fisheye's rays stay within 180 degrees of the axis), and Newton's steps must
    have converged there (distort(undistort(p)) within ``ROUND_TRIP_PIXELS`` of p)."""
    lens = intrinsics.to(torch.float64)
    if not bool(lens.is_distorted()):
        return None
    fisheye, distortion = bool(lens.fisheye), lens.distortion
    p_d = normalized_coordinates(border_pixels(height, width), lens)
    needed = float(torch.linalg.vector_norm(p_d, dim=-1).max())
    coefficients = ", ".join(f"{name}={float(v):.4g}" for name, v in zip(SLOTS, distortion) if v != 0) or "none"
    where, reach = radial_reach(distortion, fisheye)
    if needed >= reach:
        if fisheye and where >= torch.pi:
            return (f"its image reaches a distorted radius of {needed:.4g}, beyond the {reach:.4g} its distortion "
                    f"({coefficients}) gives 180 degrees from the axis")
        unit = "radians from the axis" if fisheye else "(normalized radius)"
        return (f"its distortion ({coefficients}) folds the image over itself: the radial map stops increasing at "
                f"{where:.4g} {unit}, at a distorted radius of {reach:.4g}, inside the image (which reaches "
                f"{needed:.4g})")
    if fisheye:
        theta_d = torch.linalg.vector_norm(p_d, dim=-1)
        theta_back, _ = _fisheye_angle(distortion, undistort_angle(theta_d, distortion))
        miss = (theta_back - theta_d).abs() * lens.params[:2].max()
    else:
        p = undistort_perspective(p_d, distortion)
        miss = ((distort(p, distortion, lens.fisheye) - p_d) * lens.params[:2]).abs().amax(-1)
    error = float(miss.max())
    if not error <= ROUND_TRIP_PIXELS:
        return (f"its distortion ({coefficients}) could not be inverted: undistorting and distorting again misses "
                f"by {error:.3g} pixels")
    return None
