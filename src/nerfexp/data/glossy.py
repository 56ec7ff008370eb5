"""The glossy scene: strongly view-dependent content rendered exactly by analytic ray tracing.

World z is up and every object lies inside a ball of radius ``SCENE_RADIUS`` around the origin,
with the cameras of the built-in scene (``procedural.scene_cameras``): a round base (a flat
cylinder) with a clear-coated checkerboard, a near-perfect mirror sphere standing on it, and a
tilted glossy torus standing beside the sphere. Reflected rays that leave the scene see a smooth
procedural sky (``environment``): a vertical gradient, a coloured horizon band, a few bright soft
windows and a soft sun where the light is. Primary rays that miss every object are transparent.

Shading of a surface point seen along ``d`` with unit normal ``n`` (``surface_colour``)::

    rgb = (1 - F) diffuse + F tint L(r) + k_s max(n.h, 0)^P [n.l > 0],   r = d - 2 (d.n) n,
    F = F0 + (1 - F0) (1 - n.v)^5  (Schlick),  v = -d,  diffuse = procedural.shade without highlight,

where ``L(r)`` is what the reflected ray sees: for the first ``bounces`` reflections the next surface
(shaded the same way) or the environment; a reflection beyond those sees the environment only, as if
no object were in the way. There are no shadows (as in the built-in scene).

Conventions for the whole module (those of ``procedural``): rays are ``origins`` and unit
``directions`` [..., 3], float64 where exactness matters; an intersection returns ``(t, normal)``:
``t`` [...] the distance to the first hit in front of the origin (``inf`` for a miss) and
``normal`` [..., 3] the unit outward normal there (zero for a miss). Objects are indexed in the
order base, mirror, torus (``intersect_glossy``).
"""

import functools
import math

import torch
from torch import Tensor

from nerfexp.data.procedural import (
    LIGHT_DIRECTION,
    checker,
    hit_or_miss,
    intersect_cylinder,
    intersect_sphere,
    load_procedural,
    nearest_hit,
    render_rgba,
    shade,
    unit,
)
from nerfexp.data.views import Views
from nerfexp.geometry.lenses import Intrinsics

SCENE_RADIUS = 1.3  # every object lies inside this ball around the origin

BASE = ((0.0, 0.0), 1.0, -0.65, -0.5)  # centre (x, y), radius, bottom z, top z; objects stand on the top
BASE_CHECKER_SIZE = 0.16  # side of one checker cube; the top (z = -0.5) lies inside a row of cubes, not on a face
BASE_COLOURS = ((0.9, 0.88, 0.82), (0.16, 0.18, 0.27))
MIRROR = ((-0.3, -0.3, -0.1), 0.4)  # centre, radius: it touches the base's top
MIRROR_TINT = (1.0, 0.95, 0.86)  # a faint gold
TORUS_MAJOR, TORUS_MINOR = 0.32, 0.1  # radius of the ring's centre line, radius of the tube
TORUS_TILT = math.radians(60.0)  # the angle between the torus's axis and world z
TORUS_AXIS = (math.sin(TORUS_TILT) / math.sqrt(2), -math.sin(TORUS_TILT) / math.sqrt(2), math.cos(TORUS_TILT))
TORUS_SINK = 0.02  # how far the ring's lowest point lies below the base's top, so that it stands on it
# The lowest point of a torus with axis a lies r + R sqrt(1 - a_z^2) below its centre.
TORUS_CENTRE = (0.4, 0.35, BASE[3] - TORUS_SINK + TORUS_MINOR + TORUS_MAJOR * math.sin(TORUS_TILT))
TORUS_COLOUR = (0.08, 0.55, 0.35)

F0 = (0.04, 0.9, 0.05)  # Schlick's reflectance at normal incidence: clear coat, mirror, torus
TINT = ((1.0, 1.0, 1.0), MIRROR_TINT, (1.0, 1.0, 1.0))  # colour of the reflection on each object
SPECULAR = (0.0, 0.0, 0.9)  # k_s of the sharp white Blinn-Phong highlight on each object
SHININESS = 200.0  # its exponent P
BOUNCES = 2  # reflections traced beyond the primary hit

SKY_ZENITH = (0.2, 0.38, 0.78)
SKY_HORIZON = (0.72, 0.8, 0.9)
GROUND_HORIZON = (0.42, 0.36, 0.3)
GROUND_NADIR = (0.12, 0.1, 0.09)
HORIZON_SOFTNESS = 0.03  # sine of the elevation over which ground blends into sky (a hard edge would alias)
HORIZON_BAND = ((0.9, 0.4, 0.15), 0.08, 3)  # colour, half-width (sine of elevation), lobes around the horizon
WINDOWS = (  # azimuth, elevation, half width, half height (radians), colour added
    (0.3, 0.35, 0.25, 0.15, (0.9, 0.9, 0.85)),
    (2.2, 0.6, 0.15, 0.3, (0.75, 0.85, 1.0)),
    (3.8, 0.2, 0.35, 0.1, (1.0, 0.75, 0.5)),
    (5.0, 1.0, 0.2, 0.2, (0.6, 1.0, 0.7)),
)
WINDOW_SOFTNESS = 0.1  # width of a window's edge as a fraction of its half size
SUN = (0.08, (1.0, 0.95, 0.8))  # angular radius (radians) of the soft sun in LIGHT_DIRECTION, its colour

# Sphere tracing stops this close to the torus (world units): far below a sub-pixel's footprint
# (about 1e-2 at 100 pixels and supersample 2), and Newton steps then refine the hit.
TRACE_TOLERANCE = 1e-6
# A ray that passes the torus at a distance h needs about sqrt(2 r h) / h steps to get by; after this
# many it is counted as a miss, which misjudges only rays passing within about 1e-5 of the surface.
MAX_TRACE_STEPS = 200
NEWTON_STEPS = 2  # from within TRACE_TOLERANCE of a root, two steps reach float64 precision
# A Newton step is at most this long: near-tangent rays (n.d ~ 0) would otherwise jump far along the ray.
NEWTON_MAX_STEP = 100 * TRACE_TOLERANCE
# Secondary rays start this far out along the normal: well above TRACE_TOLERANCE, so a ray leaving the
# torus does not stop on it at once, and far below a sub-pixel's footprint.
SURFACE_OFFSET = 1e-4


# ---- the torus ----


def torus_frame(axis, dtype=torch.float64) -> Tensor:
    """Rotation [3, 3] whose rows are an orthonormal frame (u, v, a), a = unit(axis): ``x @ frame.T``
    writes world vectors in the torus's frame, where its axis is z; ``x_local @ frame`` maps them back."""
    a = unit(torch.as_tensor(axis, dtype=dtype))
    helper = torch.tensor([1.0, 0.0, 0.0] if abs(float(a[0])) < 0.9 else [0.0, 1.0, 0.0], dtype=dtype)
    u = unit(torch.linalg.cross(helper, a))
    return torch.stack([u, torch.linalg.cross(a, u), a])


def torus_sdf(points: Tensor, major: float, minor: float) -> Tensor:
    """Signed distance [...] of local points [..., 3] to the torus around z: sqrt((rho - R)^2 + z^2) - r,
    rho = sqrt(x^2 + y^2). It is exact (1-Lipschitz), so a step of its value never crosses the surface."""
    rho = torch.linalg.vector_norm(points[..., :2], dim=-1)
    return torch.hypot(rho - major, points[..., 2]) - minor


def torus_normal(points: Tensor, major: float) -> Tensor:
    """Unit outward normal [..., 3] at local points [..., 3] of the torus around z: the direction from
    the nearest point of the centre circle, R (x, y, 0) / rho, to the point."""
    rho = torch.linalg.vector_norm(points[..., :2], dim=-1, keepdim=True).clamp_min(torch.finfo(points.dtype).tiny)
    core = torch.cat([major * points[..., :2] / rho, torch.zeros_like(rho)], -1)
    return unit(points - core)


def _torus_bounds(q: Tensor, d: Tensor, major: float, minor: float) -> tuple[Tensor, Tensor]:
    """The part [start, end] (each [N]) of local rays ``q + t d`` (q, d [N, 3]) with t >= 0 that lies in
    both the ball |x| <= R + r and the slab |z| <= r holding the torus; start > end where there is none."""
    b = (q * d).sum(-1)
    disc = b * b - ((q * q).sum(-1) - (major + minor) ** 2)
    root = torch.sqrt(disc.clamp_min(0))
    inside = q[..., 2].abs() <= minor
    dz = d[..., 2]
    safe_dz = torch.where(dz == 0, 1.0, dz)
    t_bottom, t_top = (-minor - q[..., 2]) / safe_dz, (minor - q[..., 2]) / safe_dz
    flat_lo, flat_hi = torch.where(inside, -torch.inf, torch.inf), torch.where(inside, torch.inf, -torch.inf)
    slab_lo = torch.where(dz == 0, flat_lo, torch.minimum(t_bottom, t_top))
    slab_hi = torch.where(dz == 0, flat_hi, torch.maximum(t_bottom, t_top))
    start = torch.maximum(torch.maximum(-b - root, slab_lo), torch.zeros_like(b))
    end = torch.where(disc >= 0, torch.minimum(-b + root, slab_hi), -torch.inf)
    return start, end


def _sphere_trace(q: Tensor, d: Tensor, start: Tensor, end: Tensor, major: float, minor: float) -> Tensor:
    """t [N] where local rays (q, d [N, 3]) first come within TRACE_TOLERANCE of the torus, marching from
    ``start`` by the signed distance; ``inf`` where they pass ``end`` or take MAX_TRACE_STEPS steps."""
    t = torch.full_like(start, torch.inf)
    live = torch.nonzero(start <= end).squeeze(-1)  # indices of the rays still marching
    t_live = start[live]
    for _ in range(MAX_TRACE_STEPS):
        if live.numel() == 0:
            break
        distance = torus_sdf(q[live] + t_live[:, None] * d[live], major, minor)
        arrived = distance < TRACE_TOLERANCE
        t[live[arrived]] = t_live[arrived]
        t_live = t_live + distance
        going = ~arrived & (t_live <= end[live])
        live, t_live = live[going], t_live[going]
    return t


def _newton(q: Tensor, d: Tensor, t: Tensor, major: float, minor: float) -> Tensor:
    """t [N] refined by NEWTON_STEPS steps t <- t - g / g' on g(t) = torus_sdf(q + t d), g' = n.d, each
    at most NEWTON_MAX_STEP long, and none where the ray does not run into the surface (g' >= 0)."""
    for _ in range(NEWTON_STEPS):
        points = q + t[:, None] * d
        slope = (torus_normal(points, major) * d).sum(-1)
        step = -torus_sdf(points, major, minor) / slope.clamp_max(-torch.finfo(t.dtype).tiny)
        t = t + torch.where(slope < 0, step.clamp(-NEWTON_MAX_STEP, NEWTON_MAX_STEP), 0.0)
    return t


def intersect_torus(
    origins: Tensor, directions: Tensor, centre, major: float, minor: float, axis=(0.0, 0.0, 1.0)
) -> tuple[Tensor, Tensor]:
    """First hit with the torus (rho - R)^2 + z^2 = r^2 around ``axis`` through ``centre`` (rho, z:
    distances from and along the axis), R = ``major`` > r = ``minor``.

    The quartic is solved by sphere tracing the exact signed distance (``torus_sdf``) from where the ray
    enters the ball of radius R + r and the slab |z| <= r around the torus, to within TRACE_TOLERANCE of
    the first root (a 1-Lipschitz distance never steps past it), then Newton steps (``_newton``). The
    normal is exact at the point found (``torus_normal``). Example: a horizontal torus at 0 with R = 1,
    r = 0.25: o = (3, 0, 0), d = (-1, 0, 0) -> t = 1.75, n = (1, 0, 0); o = (0, 0, 3), d = (0, 0, -1)
    passes through the hole -> t = inf, n = 0.
    """
    shape = origins.shape[:-1]
    frame = torus_frame(axis, origins.dtype)
    q = (origins - torch.as_tensor(centre, dtype=origins.dtype)).reshape(-1, 3) @ frame.T  # [N, 3], local
    d = directions.reshape(-1, 3) @ frame.T
    t = _sphere_trace(q, d, *_torus_bounds(q, d, major, minor), major, minor)
    hit = torch.isfinite(t)
    t[hit] = _newton(q[hit], d[hit], t[hit], major, minor)
    normal = torch.zeros_like(q)
    normal[hit] = torus_normal(q[hit] + t[hit, None] * d[hit], major) @ frame
    return hit_or_miss(hit.reshape(shape), t.reshape(shape), normal.reshape(*shape, 3))


def intersect_glossy(origins: Tensor, directions: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """First hit with the scene: (t [...], normal [..., 3], object index [...]): base, mirror, torus."""
    return nearest_hit([
        intersect_cylinder(origins, directions, *BASE),
        intersect_sphere(origins, directions, *MIRROR),
        intersect_torus(origins, directions, TORUS_CENTRE, TORUS_MAJOR, TORUS_MINOR, TORUS_AXIS),
    ])


# ---- the environment and the surfaces ----


def _soft_box(offset: Tensor, half: float) -> Tensor:
    """Weight [...] in [0, 1]: about 1 for |offset| < half, 0 beyond, with an edge WINDOW_SOFTNESS * half wide."""
    return torch.sigmoid((1 - offset.abs() / half) / WINDOW_SOFTNESS)


def environment(directions: Tensor) -> Tensor:
    """Colour [..., 3] in [0, 1] of the sky seen along unit ``directions`` [..., 3] (see the module's
    docstring): ground below and a blue gradient above the horizon, blended over HORIZON_SOFTNESS; a
    horizon band with HORIZON_BAND's lobes around it; the soft WINDOWS; the sun in LIGHT_DIRECTION."""
    dtype = directions.dtype
    x, y, z = directions.unbind(-1)
    z = z.clamp(-1, 1)
    colour = {name: torch.tensor(c, dtype=dtype) for name, c in (
        ("zenith", SKY_ZENITH), ("horizon", SKY_HORIZON), ("ground", GROUND_HORIZON), ("nadir", GROUND_NADIR))}
    sky = torch.lerp(colour["horizon"], colour["zenith"], z.clamp_min(0).sqrt()[..., None])
    ground = torch.lerp(colour["ground"], colour["nadir"], (-z).clamp_min(0).sqrt()[..., None])
    rgb = torch.lerp(ground, sky, torch.sigmoid(z / HORIZON_SOFTNESS)[..., None])
    azimuth, elevation = torch.atan2(y, x), torch.asin(z)
    band_colour, band_width, lobes = HORIZON_BAND
    band = torch.exp(-((z / band_width) ** 2)) * (0.5 + 0.5 * torch.cos(lobes * azimuth))
    rgb = rgb + band[..., None] * torch.tensor(band_colour, dtype=dtype)
    for centre_azimuth, centre_elevation, half_width, half_height, window_colour in WINDOWS:
        across = torch.remainder(azimuth - centre_azimuth + math.pi, 2 * math.pi) - math.pi  # in [-pi, pi)
        weight = _soft_box(across, half_width) * _soft_box(elevation - centre_elevation, half_height)
        rgb = rgb + weight[..., None] * torch.tensor(window_colour, dtype=dtype)
    sun_radius, sun_colour = SUN
    light = unit(torch.tensor(LIGHT_DIRECTION, dtype=dtype))
    sun = torch.exp(-2 * (1 - (directions * light).sum(-1)) / sun_radius**2)  # 2 (1 - cos a) ~ a^2
    return (rgb + sun[..., None] * torch.tensor(sun_colour, dtype=dtype)).clamp(0, 1)


def reflect(directions: Tensor, normals: Tensor) -> Tensor:
    """Mirror directions [..., 3]: r = d - 2 (d.n) n. Example: d = (1, 0, -1) / sqrt 2, n = z -> (1, 0, 1) / sqrt 2."""
    return directions - 2 * (directions * normals).sum(-1, keepdim=True) * normals


def schlick(cosines: Tensor, f0: Tensor) -> Tensor:
    """Schlick's Fresnel reflectance [...]: F = F0 + (1 - F0) (1 - cos)^5, cos = n.v in [0, 1]."""
    return f0 + (1 - f0) * (1 - cosines) ** 5


def albedo(points: Tensor, normals: Tensor, index: Tensor) -> Tensor:
    """Diffuse colour [..., 3] of the surface points [..., 3] of objects ``index`` [...]: the base's 3-D
    checker (cubes sampled half a cube inside the surface, away from the faces they would flicker on), a
    black mirror, the torus's colour."""
    base = checker((points - 0.5 * BASE_CHECKER_SIZE * normals) / BASE_CHECKER_SIZE, BASE_COLOURS)
    mirror, torus = (torch.tensor(c, dtype=points.dtype) for c in ((0.0, 0.0, 0.0), TORUS_COLOUR))
    colours = torch.stack(torch.broadcast_tensors(base, mirror, torus), -2)  # [..., 3 objects, 3]
    return torch.gather(colours, -2, index[..., None, None].expand(*index.shape, 1, 3)).squeeze(-2)


def surface_colour(points: Tensor, normals: Tensor, view_dirs: Tensor, index: Tensor, incoming: Tensor) -> Tensor:
    """Colour [..., 3] in [0, 1] of surface points [..., 3] of objects ``index`` [...] seen from ``view_dirs``
    [..., 3] (surface to eye), given the colour ``incoming`` [..., 3] seen along the mirror direction:
    (1 - F) diffuse + F tint incoming + k_s max(n.h, 0)^P [n.l > 0], F by ``schlick`` with F0[index]."""
    dtype = points.dtype
    diffuse = shade(normals, view_dirs, albedo(points, normals, index), torch.zeros_like(index, dtype=dtype))
    fresnel = schlick((normals * view_dirs).sum(-1).clamp(0, 1), torch.tensor(F0, dtype=dtype)[index])[..., None]
    light = unit(torch.tensor(LIGHT_DIRECTION, dtype=dtype))
    n_dot_h = (normals * unit(light + view_dirs)).sum(-1).clamp_min(0)
    highlight = torch.tensor(SPECULAR, dtype=dtype)[index] * n_dot_h**SHININESS * ((normals * light).sum(-1) > 0)
    tint = torch.tensor(TINT, dtype=dtype)[index]
    return ((1 - fresnel) * diffuse + fresnel * tint * incoming + highlight[..., None]).clamp(0, 1)


def _trace(origins: Tensor, directions: Tensor, bounces: int, background: Tensor) -> tuple[Tensor, Tensor]:
    """Colour [N, 3] and hit mask [N] of rays [N, 3]: ``background`` [N, 3] where they miss, else the
    first surface by ``surface_colour``, whose mirror ray is traced on while ``bounces`` > 0 and sees
    the environment only after that."""
    t, normals, index = intersect_glossy(origins, directions)
    hit = torch.isfinite(t)
    o, d, n = origins[hit], directions[hit], normals[hit]
    points = o + t[hit, None] * d
    mirrored = reflect(d, n)
    if bounces > 0:
        incoming, _ = _trace(points + SURFACE_OFFSET * n, mirrored, bounces - 1, environment(mirrored))
    else:
        incoming = environment(mirrored)
    rgb = background.clone()
    rgb[hit] = surface_colour(points, n, -d, index[hit], incoming)
    return rgb, hit


def trace_glossy(origins: Tensor, directions: Tensor, bounces: int = BOUNCES) -> tuple[Tensor, Tensor]:
    """Colour [..., 3] (zero on a miss) and alpha [...] (1 on a hit, 0 on a miss) of primary rays [..., 3]
    through the scene, with ``bounces`` reflections traced (0: surfaces reflect the environment only)."""
    shape = origins.shape[:-1]
    o, d = origins.reshape(-1, 3), directions.reshape(-1, 3)
    rgb, hit = _trace(o, d, bounces, torch.zeros_like(o))
    return rgb.reshape(*shape, 3), hit.reshape(shape).to(origins.dtype)


# ---- images and views ----


def render_glossy_rgba(c2w: Tensor, height: int, width: int, intrinsics: Intrinsics, supersample: int = 2,
                       bounces: int = BOUNCES) -> Tensor:
    """Straight-alpha images [N, H, W, 4] float32 of the glossy scene seen by cameras ``c2w`` [N, 4, 4]
    (``procedural.render_rgba`` with ``trace_glossy``)."""
    return render_rgba(c2w, height, width, intrinsics, supersample, functools.partial(trace_glossy, bounces=bounces))


def load_glossy(split: str, n_views: int, height: int, width: int, supersample: int = 2,
                lens: Intrinsics | None = None) -> Views:
    """``n_views`` rendered views of ``split`` from the built-in scene's cameras through ``lens`` (None: the
    Blender pinhole), as ``Views``."""
    return load_procedural(split, n_views, height, width, supersample, trace_glossy, lens)
