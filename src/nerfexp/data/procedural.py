"""The built-in scene: a small still life rendered exactly by analytic ray intersection.

World z is up and every object lies inside a ball of radius ``SCENE_RADIUS`` around the origin:
a pedestal slab with a fine checkerboard, a red sphere with a strong white Blinn-Phong highlight,
a smaller sphere with a latitude/longitude checker, and four thin coloured rods. The slab and the
small sphere carry a faint sheen (the rods none), so view dependence matters over a good part of
each image, as it does in the Blender scenes. Objects are opaque and the background is transparent.

Conventions for the whole module: rays are ``origins`` and unit ``directions`` [..., 3], starting
outside every shape. An intersection returns ``(t, normal)``: ``t`` [...] the distance to the
first hit in front of the origin (``inf`` for a miss) and ``normal`` [..., 3] the unit outward
normal there (zero for a miss).
"""

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor
from tqdm import tqdm

from nerfexp.data.base import Scene
from nerfexp.data.blender import BLENDER_HALF_SIDE
from nerfexp.data.views import Views
from nerfexp.domains import COUNT, Memory, Rule, choice
from nerfexp.geometry.cameras import camera_rays, focal_from_fov, look_at
from nerfexp.geometry.lenses import Intrinsics, distortion_vector
from nerfexp.memory import scene_bytes

NEAR, FAR = 2.0, 6.0
OCCLUDER_SIDE = 0.3  # a transient occluder's side, as a fraction of the shorter image side (``occlude``)
OCCLUDER_COLOUR = (1.0, 0.0, 1.0)  # magenta: a colour the scene does not have
CAMERA_ANGLE_X = 0.6911112070083618
CAMERA_RADIUS = 4.0
SCENE_RADIUS = 1.3

SLAB = ((-0.75, -0.75, -0.7), (0.75, 0.75, -0.5))  # box corners; objects stand on z = -0.5
CHECKER_SIZE = 0.15  # side of one checker square
CHECKER_COLOURS = ((0.25, 0.35, 0.7), (0.9, 0.7, 0.35))
GLOSSY = ((0.1, 0.1, -0.05), 0.45, (0.75, 0.08, 0.08))  # centre, radius, colour
STRIPED = ((-0.45, -0.45, -0.25), 0.25)  # centre, radius
STRIPED_CELLS = (12, 6)  # checker cells around the equator and from pole to pole
STRIPED_COLOURS = ((0.9, 0.9, 0.85), (0.25, 0.55, 0.3))
RODS = (  # (x, y), radius, top z, colour; each stands on the slab
    ((0.6, 0.6), 0.04, 0.45, (0.95, 0.85, 0.1)),
    ((0.6, -0.55), 0.035, 0.2, (0.1, 0.8, 0.9)),
    ((-0.55, 0.55), 0.045, 0.6, (0.85, 0.2, 0.8)),
    ((-0.65, 0.0), 0.03, 0.3, (0.3, 0.9, 0.3)),
)

LIGHT_DIRECTION = (0.45, -0.35, 0.82)  # towards the light; normalised where used
AMBIENT = 0.25
SPECULAR = (0.6, 0.8, 0.4, 0.0)  # k_s of the white highlight on the slab, glossy sphere, striped sphere, rods
SHININESS = 10.0

TRAIN_ELEVATIONS = (math.radians(5.0), math.radians(80.0))
ORBIT_ELEVATION = math.radians(30.0)
ORBIT_OFFSETS = {"val": 1.0, "test": 2.0}  # radians; irrational multiples of 2 pi never coincide
GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))
# Per-image appearance changes (``vary_appearance``): an image's exposure 2^u, u uniform in +-EXPOSURE_STOPS stops,
# and each channel's white balance 2^v, v uniform in +-WHITE_BALANCE_STOPS. APPEARANCE_CHANGES: none; train (the
# training images', the others neutral); all (every image's, as photographs in the wild: NeRF-W's setting)
APPEARANCE_CHANGES = ("none", "train", "all")
EXPOSURE_STOPS = 1.0
WHITE_BALANCE_STOPS = 0.5
APPEARANCE_SEEDS = {"train": 0, "val": 1, "test": 2}  # each split's gains: the same images whatever the run's seed
RAY_CHUNK = 2**16  # rays traced at once
RAYS_PER_GROUP = 2**20  # sub-pixel rays per rendered group of views


def unit(v: Tensor) -> Tensor:
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(torch.finfo(v.dtype).tiny)


def objects_box() -> Tensor:
    """The smallest axis-aligned box [2, 3] (lower, upper corner) holding every object, float32: the slab,
    the two spheres and the rods (cylinders standing on the slab's top, z = SLAB[1][2])."""
    lower, upper = [list(SLAB[0])], [list(SLAB[1])]
    for centre, radius in (GLOSSY[:2], STRIPED):
        lower.append([c - radius for c in centre])
        upper.append([c + radius for c in centre])
    for (x, y), radius, top, _ in RODS:
        lower.append([x - radius, y - radius, SLAB[1][2]])
        upper.append([x + radius, y + radius, top])
    return torch.stack([torch.tensor(lower).amin(0), torch.tensor(upper).amax(0)])


def hit_or_miss(hit: Tensor, t: Tensor, normal: Tensor) -> tuple[Tensor, Tensor]:
    return torch.where(hit, t, torch.inf), torch.where(hit[..., None], normal, 0.0)


def intersect_sphere(origins: Tensor, directions: Tensor, centre, radius: float) -> tuple[Tensor, Tensor]:
    """First hit with the sphere |x - centre| = radius.

    With q = o - centre: t = -b - sqrt(b^2 - c), b = d.q, c = |q|^2 - r^2 (|d| = 1).
    Example: o = (0, 0, 4), d = (0, 0, -1), centre 0, r = 1 -> t = 3, normal (0, 0, 1).
    """
    q = origins - torch.as_tensor(centre, dtype=origins.dtype)
    b = (directions * q).sum(-1)
    disc = b * b - ((q * q).sum(-1) - radius**2)
    t = -b - torch.sqrt(disc.clamp_min(0))
    return hit_or_miss((disc >= 0) & (t > 0), t, (q + t[..., None] * directions) / radius)


def intersect_box(origins: Tensor, directions: Tensor, lo, hi) -> tuple[Tensor, Tensor]:
    """First hit with the axis-aligned box lo <= x <= hi (slab method).

    Per axis k the ray is between the planes for t in [min(t_lo, t_hi), max(t_lo, t_hi)], with
    t_lo = (lo_k - o_k) / d_k (+-inf where d_k = 0); it enters at t_in = max_k min(.) and leaves
    at t_out = min_k max(.); a hit needs 0 < t_in <= t_out. The normal is -sign(d_k) e_k on the
    axis that sets t_in. Example: o = (3, 0, 0), d = (-1, 0, 0), box [-1, 1]^3 -> t = 2, n = (1, 0, 0).
    """
    t_lo = (torch.as_tensor(lo, dtype=origins.dtype) - origins) / directions
    t_hi = (torch.as_tensor(hi, dtype=origins.dtype) - origins) / directions
    t_in, axis = torch.minimum(t_lo, t_hi).max(-1)
    t_out = torch.maximum(t_lo, t_hi).amin(-1)
    normal = -torch.sign(directions) * torch.nn.functional.one_hot(axis, 3).to(origins.dtype)
    return hit_or_miss((t_in > 0) & (t_in <= t_out), t_in, normal)


def intersect_cylinder(
    origins: Tensor, directions: Tensor, centre_xy, radius: float, z_bottom: float, z_top: float
) -> tuple[Tensor, Tensor]:
    """First hit with the closed vertical cylinder |xy - centre_xy| <= radius, z_bottom <= z <= z_top.

    Side: with q = o - centre, a = dx^2 + dy^2, b = dx qx + dy qy, c = qx^2 + qy^2 - r^2, the
    entering root t = (-b - sqrt(b^2 - a c)) / a, kept if its z lies between the caps. Caps:
    t = (z_cap - oz) / dz, kept if the hit lies in the disc. The nearest of the three wins.
    Example: o = (2, 0, 0.5), d = (-1, 0, 0), r = 0.5, z in [0, 1] -> t = 1.5, n = (1, 0, 0).
    """
    q = origins - torch.tensor([*centre_xy, 0.0], dtype=origins.dtype)
    qx, qy, qz = q.unbind(-1)
    dx, dy, dz = directions.unbind(-1)
    a = dx * dx + dy * dy
    b = dx * qx + dy * qy
    disc = b * b - a * (qx * qx + qy * qy - radius**2)
    t_side = (-b - torch.sqrt(disc.clamp_min(0))) / a.clamp_min(torch.finfo(a.dtype).tiny)
    z_side = qz + t_side * dz
    side = (a > 0) & (disc >= 0) & (t_side > 0) & (z_side >= z_bottom) & (z_side <= z_top)
    candidates = [hit_or_miss(side, t_side, torch.stack([qx + t_side * dx, qy + t_side * dy, 0 * qz], -1) / radius)]
    for z_cap, up in ((z_top, 1.0), (z_bottom, -1.0)):
        t_cap = (z_cap - qz) / torch.where(dz == 0, 1.0, dz)
        in_disc = (qx + t_cap * dx) ** 2 + (qy + t_cap * dy) ** 2 <= radius**2
        normal = torch.tensor([0.0, 0.0, up], dtype=origins.dtype).expand_as(q)
        candidates.append(hit_or_miss((dz != 0) & (t_cap > 0) & in_disc, t_cap, normal))
    return nearest_hit(candidates)[:2]


def nearest_hit(hits: list[tuple[Tensor, Tensor]]) -> tuple[Tensor, Tensor, Tensor]:
    """The nearest of K intersections ``(t, normal)``: (t [...], normal [..., 3], index [...])."""
    ts = torch.stack([t for t, _ in hits], -1)  # [..., K]
    normals = torch.stack([n for _, n in hits], -2)  # [..., K, 3]
    t, index = ts.min(-1)
    normal = torch.gather(normals, -2, index[..., None, None].expand(*index.shape, 1, 3)).squeeze(-2)
    return t, normal, index


def intersect_scene(origins: Tensor, directions: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """First hit with the scene: (t [...], normal [..., 3], object index [...]).

    Objects in index order: slab, glossy sphere, striped sphere, the rods.
    """
    hits = [
        intersect_box(origins, directions, *SLAB),
        intersect_sphere(origins, directions, *GLOSSY[:2]),
        intersect_sphere(origins, directions, *STRIPED),
    ]
    hits += [intersect_cylinder(origins, directions, xy, r, SLAB[1][2], top) for xy, r, top, _ in RODS]
    return nearest_hit(hits)


def _box_distance(points: Tensor, lower, upper) -> Tensor:
    lower, upper = points.new_tensor(lower), points.new_tensor(upper)
    q = (points - (lower + upper) / 2).abs() - (upper - lower) / 2  # per axis: outside the slab if positive
    return q.clamp_min(0).norm(dim=-1) + q.amax(-1).clamp_max(0)


def _sphere_distance(points: Tensor, centre, radius: float) -> Tensor:
    return (points - points.new_tensor(centre)).norm(dim=-1) - radius


def _rod_distance(points: Tensor, centre_xy, radius: float, bottom: float, top: float) -> Tensor:
    """A vertical cylinder: the box distance in (distance from the axis, height)."""
    radial = (points[..., :2] - points.new_tensor(centre_xy)).norm(dim=-1) - radius
    height = (points[..., 2] - (bottom + top) / 2).abs() - (top - bottom) / 2
    q = torch.stack([radial, height], -1)
    return q.clamp_min(0).norm(dim=-1) + q.amax(-1).clamp_max(0)


def signed_distances(points: Tensor) -> Tensor:
    """The exact signed distance [..., K] of ``points`` [..., 3] to each object, negative inside, in
    ``intersect_scene``'s order (slab, glossy sphere, striped sphere, rods): the scene's true geometry, what
    an exported surface is measured against. The distance to the scene is the minimum over K."""
    columns = [_box_distance(points, *SLAB), _sphere_distance(points, *GLOSSY[:2]), _sphere_distance(points, *STRIPED)]
    columns += [_rod_distance(points, xy, r, SLAB[1][2], top) for xy, r, top, _ in RODS]
    return torch.stack(columns, -1)


def checker(cells: Tensor, colours) -> Tensor:
    """Alternating colours [..., 3] by the parity of the summed integer cell coordinates [..., D]."""
    odd = (torch.floor(cells).sum(-1) % 2)[..., None]
    first, second = (torch.tensor(c, dtype=cells.dtype) for c in colours)
    return first + odd * (second - first)


def albedo(points: Tensor, normals: Tensor, index: Tensor) -> Tensor:
    """Diffuse colour [..., 3] of the surface points [..., 3] of objects ``index`` [...]."""
    # Half a square inside the surface, cells are away from the face planes they would flicker on.
    slab = checker((points - 0.5 * CHECKER_SIZE * normals) / CHECKER_SIZE, CHECKER_COLOURS)
    longitude = torch.atan2(normals[..., 1], normals[..., 0]) + math.pi  # [0, 2 pi]
    latitude = torch.acos(normals[..., 2].clamp(-1, 1))  # [0, pi]
    cells = torch.stack([longitude / (2 * math.pi) * STRIPED_CELLS[0], latitude / math.pi * STRIPED_CELLS[1]], -1)
    glossy, rods = (torch.tensor(c, dtype=points.dtype) for c in (GLOSSY[2], [c for *_, c in RODS]))
    table = [slab, glossy, checker(cells, STRIPED_COLOURS), *rods]  # the order of intersect_scene
    colours = torch.stack(torch.broadcast_tensors(*table), -2)  # [..., K, 3]
    return torch.gather(colours, -2, index[..., None, None].expand(*index.shape, 1, 3)).squeeze(-2)


def shade(normals: Tensor, view_dirs: Tensor, albedo: Tensor, specular: Tensor) -> Tensor:
    """Ambient + Lambert + Blinn-Phong colour [..., 3] under the directional light, clipped to [0, 1].

    rgb = albedo (A + (1 - A) max(n.l, 0)) + k_s max(n.h, 0)^p [n.l > 0], h = unit(l + v).
    ``view_dirs`` [..., 3] point from the surface to the eye; ``specular`` [...] is k_s.
    """
    light = unit(torch.tensor(LIGHT_DIRECTION, dtype=normals.dtype))
    n_dot_l = (normals * light).sum(-1)
    n_dot_h = (normals * unit(light + view_dirs)).sum(-1).clamp_min(0)
    highlight = specular * n_dot_h**SHININESS * (n_dot_l > 0)
    rgb = albedo * (AMBIENT + (1 - AMBIENT) * n_dot_l.clamp_min(0))[..., None] + highlight[..., None]
    return rgb.clamp(0, 1)


def trace(origins: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
    """Colour [..., 3] (zero on a miss) and hit mask [...] of rays through the scene."""
    t, normals, index = intersect_scene(origins, directions)
    hit = torch.isfinite(t)
    points = origins + torch.where(hit, t, 0.0)[..., None] * directions
    specular = torch.tensor(SPECULAR[:3] + SPECULAR[3:] * len(RODS), dtype=origins.dtype)[index]
    rgb = shade(normals, -directions, albedo(points, normals, index), specular)
    return torch.where(hit[..., None], rgb, 0.0), hit


Tracer = Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]  # rays [R, 3] x 2 -> (rgb [R, 3], hit or alpha [R])


def render_rgba(c2w: Tensor, height: int, width: int, intrinsics: Intrinsics, supersample: int = 2,
                tracer: Tracer = trace) -> Tensor:
    """Straight-alpha images [N, H, W, 4] float32 of the scene seen by cameras ``c2w`` [N, 4, 4].

    ``intrinsics``: the cameras' lenses (batch shape [] or [N]). Each pixel averages ``supersample`` x
    ``supersample`` rays through the centres of its
    sub-pixels: alpha is the covered fraction, rgb the mean colour of the covered sub-pixels.
    ``tracer`` (rays -> (rgb, hit)) is the scene: this module's ``trace``, or another analytic one
    (``nerfexp.data.glossy``).
    """
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    s = supersample
    fine = Intrinsics(intrinsics.params * s, intrinsics.distortion, intrinsics.fisheye)  # the sub-pixels' lenses
    origins, directions = camera_rays(c2w.to(torch.float64), height * s, width * s, fine)
    N = c2w.shape[0]
    chunks = zip(origins.reshape(-1, 3).split(RAY_CHUNK), directions.reshape(-1, 3).split(RAY_CHUNK))
    traced = [tracer(o, d) for o, d in chunks]
    rgb = torch.cat([c for c, _ in traced]).reshape(N, height, s, width, s, 3).sum((2, 4))
    hits = torch.cat([h for _, h in traced]).reshape(N, height, s, width, s).sum((2, 4))[..., None]
    rgb = torch.where(hits > 0, rgb / hits.clamp_min(1), 0.0)
    return torch.cat([rgb, hits / s**2], -1).float()


def scene_cameras(split: str, n: int) -> Tensor:
    """Camera-to-world matrices [n, 4, 4] float64 at distance CAMERA_RADIUS, looking at the origin.

    ``train``: a golden-angle spiral, uniform in area over elevations 5 to 80 degrees.
    ``val`` / ``test``: orbits at elevation 30 degrees, evenly spaced, at different azimuth offsets.
    """
    k = torch.arange(n, dtype=torch.float64)
    if split == "train":
        low, high = (math.sin(e) for e in TRAIN_ELEVATIONS)
        elevation = torch.asin(low + (high - low) * (k + 0.5) / n)
        azimuth = k * GOLDEN_ANGLE
    elif split in ORBIT_OFFSETS:
        elevation = torch.full_like(k, ORBIT_ELEVATION)
        azimuth = ORBIT_OFFSETS[split] + 2 * math.pi * k / n
    else:
        raise ValueError(f"unknown split {split!r}: expected one of 'train', 'val', 'test'")
    eye = CAMERA_RADIUS * torch.stack(
        [torch.cos(elevation) * torch.cos(azimuth), torch.cos(elevation) * torch.sin(azimuth), torch.sin(elevation)], -1
    )
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    return look_at(eye, torch.zeros(3, dtype=torch.float64), up)


def real_lens(height: int, width: int) -> Intrinsics:
    """A lens like a phone's, for the built-in scenes' cameras (``nerfexp-scene --lens real``): the Blender
    camera's focal length f made fx = 1.03 f and fy = 0.97 f, the principal point off the centre at
    (0.54 W, 0.47 H), and OPENCV distortion k1 = -0.12, k2 = 0.03 (barrel), p1 = 0.002, p2 = -0.003."""
    focal = focal_from_fov(width, CAMERA_ANGLE_X)
    params = torch.tensor([1.03 * focal, 0.97 * focal, 0.54 * width, 0.47 * height], dtype=torch.float64)
    distortion = distortion_vector({"k1": -0.12, "k2": 0.03, "p1": 0.002, "p2": -0.003})
    return Intrinsics(params, distortion, torch.tensor(False))


def occlude(views: Views, seed: int, colour: tuple[float, float, float] = OCCLUDER_COLOUR) -> Views:
    """``views`` with a transient occluder in each image and the mask that leaves it out: a solid square of
    ``colour``, its side ``OCCLUDER_SIDE`` of the shorter image side, at a position drawn per view from
    ``seed``; the mask is False on the square (``Views.mask``)."""
    N, H, W, _ = views.rgba.shape  # views, rows, columns, channels
    side = max(1, round(OCCLUDER_SIDE * min(H, W)))
    generator = torch.Generator().manual_seed(seed)
    rows = torch.randint(H - side + 1, (N,), generator=generator)
    cols = torch.randint(W - side + 1, (N,), generator=generator)
    rgba, mask = views.rgba.clone(), torch.ones(N, H, W, dtype=torch.bool)
    for n, (i, j) in enumerate(zip(rows.tolist(), cols.tolist())):
        rgba[n, i:i + side, j:j + side] = torch.tensor([*colour, 1.0])
        mask[n, i:i + side, j:j + side] = False
    return Views(rgba=rgba, c2w=views.c2w, intrinsics=views.intrinsics, mask=mask)


def appearance_gains(n_views: int, seed: int) -> Tensor:
    """Per-image colour gains [N, 3] (float32), drawn from ``seed``: exposure 2^u times white balance 2^v_c, u
    uniform in [-EXPOSURE_STOPS, EXPOSURE_STOPS] per image and v_c uniform in [-WHITE_BALANCE_STOPS,
    WHITE_BALANCE_STOPS] per image and channel (in stops, so that brighter and darker are equally likely)."""
    generator = torch.Generator().manual_seed(seed)
    exposure = (2 * torch.rand(n_views, 1, generator=generator) - 1) * EXPOSURE_STOPS  # [N, 1] stops
    balance = (2 * torch.rand(n_views, 3, generator=generator) - 1) * WHITE_BALANCE_STOPS  # [N, 3] stops
    return torch.exp2(exposure + balance)


def vary_appearance(views: Views, gains: Tensor) -> Views:
    """``views`` as a camera with each image's exposure and white balance would see them: image n's colours times
    ``gains[n]`` [3] (``appearance_gains``), clipped to [0, 1] as a sensor saturates; alpha and masks unchanged
    (the background, composited later, stays the scene's)."""
    rgb = (views.rgba[..., :3] * gains[:, None, None, :]).clamp(0.0, 1.0)  # [N, H, W, 3]
    return Views(rgba=torch.cat([rgb, views.rgba[..., 3:]], -1), c2w=views.c2w, intrinsics=views.intrinsics,
                 mask=views.mask)


def load_procedural(split: str, n_views: int, height: int, width: int, supersample: int = 2,
                    tracer: Tracer = trace, lens: Intrinsics | None = None) -> Views:
    """``n_views`` rendered views of ``split`` of the scene ``tracer`` (see ``render_rgba``) through the
    lens ``lens`` (shape []; None: the Blender scenes' pinhole, ``CAMERA_ANGLE_X`` wide, centred), with a
    progress bar, as ``Views``."""
    c2w = scene_cameras(split, n_views)
    focal = focal_from_fov(width, CAMERA_ANGLE_X)
    lens = Intrinsics.pinhole(focal, height, width) if lens is None else lens
    group = max(1, RAYS_PER_GROUP // (height * width * supersample**2))
    images = []
    with tqdm(total=n_views, desc=f"rendering {split}", unit="view", disable=None) as bar:
        for cameras in c2w.split(group):
            images.append(render_rgba(cameras, height, width, lens, supersample, tracer))
            bar.update(len(cameras))
    lenses = Intrinsics(*(t.expand(n_views, *t.shape).clone() for t in (lens.params, lens.distortion, lens.fisheye)))
    return Views(rgba=torch.cat(images), c2w=c2w.float(), intrinsics=lenses)


TRAIN_VIEWS = 100  # the built-in scene's training set: as many views as each Realistic Synthetic scene has


@dataclass(kw_only=True)
class ProceduralScene(Scene):
    """The built-in scene as a dataset (``data=procedural``): ``views(split)`` renders that split. With
    ``appearance_changes`` train, each training image has its own exposure and white balance (``vary_appearance``,
    the gains of ``appearance_gains``, seeded per split: ``APPEARANCE_SEEDS``), the others none; with all, every
    image has: ground truth for ``appearance=embedding``."""

    DOMAINS: ClassVar[dict[str, Rule]] = {**Scene.DOMAINS, "image_size": COUNT, "n_test": COUNT, "supersample": COUNT,
                                          "appearance_changes": choice(*APPEARANCE_CHANGES)}

    @staticmethod
    def MEMORY(config: Mapping) -> list[Memory]:
        """Its views' rays and colours, each pixel traced with ``supersample``^2 rays while it is made."""
        views = (config["n_train"] or 0) + config["n_val"] + config["n_test"]
        size = config["image_size"]
        return [(("image_size", "supersample", "n_train", "n_val", "n_test"),
                 f"a scene of {views} views of {size} x {size} pixels",
                 scene_bytes(views, size, size, config["supersample"]))]

    image_size: int = 64
    n_train: int | None = TRAIN_VIEWS  # None: the scene's whole training set, TRAIN_VIEWS views
    n_test: int = 8
    supersample: int = 2
    near: float = NEAR
    far: float = FAR
    appearance_changes: str = "none"  # train, all: those images' own exposure and white balance

    def views(self, split: str) -> Views:
        n_train = TRAIN_VIEWS if self.n_train is None else self.n_train
        n_views = {"train": n_train, "val": self.n_val, "test": self.n_test}[split]
        views = load_procedural(split, n_views, self.image_size, self.image_size, self.supersample)
        if self.appearance_changes == "all" or (split == "train" and self.appearance_changes == "train"):
            views = vary_appearance(views, appearance_gains(n_views, APPEARANCE_SEEDS[split]))
        return views

    def bounding_box(self) -> Tensor:
        """[2, 3]: Blender's [-1.5, 1.5]^3, the box of the synthetic scenes whose cameras this scene follows: it
        holds the objects (``objects_box``) with 0.75 to 0.9 of room on every side. The room matters to the
        occupancy grid: over the objects' box widened by one pixel's footprint (an edge pixel's ray can pass just
        outside the object it partly shows) the complete model trained through the grid scored lower than without
        it, and with the room it does not (measured: docs/acceleration.md, the grid's quality loss)."""
        return torch.tensor([[-BLENDER_HALF_SIDE] * 3, [BLENDER_HALF_SIDE] * 3])
