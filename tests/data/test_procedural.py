"""The built-in scene: exact intersections, shading, cameras, rendering, and its box."""

import math

import pytest
import torch

from nerfexp.data import procedural as P
from nerfexp.data.procedural import (
    FAR,
    NEAR,
    ProceduralScene,
    intersect_scene,
    objects_box,
    scene_cameras,
    signed_distances,
)
from nerfexp.geometry.cameras import camera_rays, focal_from_fov
from nerfexp.geometry.lenses import Intrinsics, distortion_vector, pixel_grid, pixel_rays

F64 = torch.float64


def ray(origin, direction):
    d = torch.tensor(direction, dtype=F64)
    return torch.tensor(origin, dtype=F64)[None], (d / d.norm())[None]


def lens(size: int) -> Intrinsics:
    """The built-in scene's camera at ``size`` x ``size`` pixels: a centred pinhole."""
    return Intrinsics.pinhole(focal_from_fov(size, P.CAMERA_ANGLE_X), size, size)


def render(c2w, size, supersample=2):
    return P.render_rgba(c2w, size, size, lens(size), supersample)


# ---- intersections, against hand-computed values ----

@pytest.mark.parametrize("origin, direction, centre, radius, t, normal", [
    ((0, 0, 4), (0, 0, -1), (0, 0, 0), 0.5, 3.5, (0, 0, 1)),  # straight on: 4 - r
    # offset by 1 from the axis of a sphere of radius 2: hits z = sqrt(4 - 1) = sqrt(3)
    ((0, 1, 4), (0, 0, -1), (0, 0, 0), 2.0, 4 - math.sqrt(3), (0, 0.5, math.sqrt(3) / 2)),
    ((1, 2, 3), (1, 0, 0), (4, 2, 3), 1.0, 2.0, (-1, 0, 0)),  # shifted centre
])
def test_sphere_hit_matches_closed_form(origin, direction, centre, radius, t, normal):
    t_hit, n_hit = P.intersect_sphere(*ray(origin, direction), centre, radius)
    torch.testing.assert_close(t_hit, torch.tensor([t], dtype=F64))
    torch.testing.assert_close(n_hit, torch.tensor([normal], dtype=F64))


@pytest.mark.parametrize("origin, direction", [
    ((0, 0, 4), (1, 0, 0)), ((0, 0, 4), (0, 0, 1)), ((0, 2.01, 4), (0, 0, -1)),
])
def test_sphere_miss_is_inf_with_zero_normal(origin, direction):
    t, n = P.intersect_sphere(*ray(origin, direction), (0, 0, 0), 2.0)
    assert t.item() == math.inf and n.abs().sum().item() == 0


@pytest.mark.parametrize("origin, direction, t, normal", [
    ((3, 0.2, 0.1), (-1, 0, 0), 2.0, (1, 0, 0)),
    ((0.3, -0.4, -5), (0, 0, 1), 4.0, (0, 0, -1)),
    # direction (1, 0.2, 0) from x = -3 reaches x = -1 after 2 units of x, at y = 0.9: t = 2 sqrt(1.04)
    ((-3, 0.5, 0), (1, 0.2, 0), 2 * math.sqrt(1.04), (-1, 0, 0)),
    ((-3, 0.5, 0), (1, 1, 0), math.inf, (0, 0, 0)),  # at x = -1 it is already at y = 2.5
    ((3, 0, 0), (1, 0, 0), math.inf, (0, 0, 0)),  # the box is behind the origin
])
def test_box_hits_match_hand_computed(origin, direction, t, normal):
    t_hit, n_hit = P.intersect_box(*ray(origin, direction), (-1, -1, -1), (1, 1, 1))
    torch.testing.assert_close(t_hit, torch.tensor([t], dtype=F64))
    torch.testing.assert_close(n_hit, torch.tensor([normal], dtype=F64))


@pytest.mark.parametrize("origin, direction, t, normal", [
    ((2, 0, 0.5), (-1, 0, 0), 1.5, (1, 0, 0)),  # side
    ((0, -3, 0.2), (0, 1, 0), 2.5, (0, -1, 0)),  # side, other way
    ((0.1, 0.2, 3), (0, 0, -1), 2.0, (0, 0, 1)),  # top cap, vertical ray
    ((0.1, 0.2, -2), (0, 0, 1), 2.0, (0, 0, -1)),  # bottom cap
    ((0, 0, 2), (0.3, 0, -1), math.sqrt(1.09), (0, 0, 1)),  # oblique onto the top at x = 0.3 < 0.5
    ((2, 0, 1.5), (-1, 0, 0), math.inf, (0, 0, 0)),  # passes above
    ((1, 0, 3), (0, 0, -1), math.inf, (0, 0, 0)),  # vertical, outside the disc
])
def test_cylinder_hits_match_hand_computed(origin, direction, t, normal):
    t_hit, n_hit = P.intersect_cylinder(*ray(origin, direction), (0, 0), 0.5, 0.0, 1.0)
    torch.testing.assert_close(t_hit, torch.tensor([t], dtype=F64))
    torch.testing.assert_close(n_hit, torch.tensor([normal], dtype=F64))


def test_cylinder_off_centre_side_hit():
    # axis at (1, 2), radius 0.25: a ray along -x at y = 2 from x = 3 hits x = 1.25 at t = 1.75
    t, n = P.intersect_cylinder(*ray((3, 2, 0.5), (-1, 0, 0)), (1, 2), 0.25, 0.0, 1.0)
    assert t.item() == pytest.approx(1.75) and n[0].tolist() == pytest.approx([1, 0, 0])


def test_every_object_lies_inside_the_scene_ball():
    # Rays whose closest approach to the origin is just outside SCENE_RADIUS must miss everything.
    g = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(20000, 3, generator=g, dtype=F64), dim=-1)
    u = torch.linalg.cross(d, torch.randn(20000, 3, generator=g, dtype=F64), dim=-1)
    u = torch.nn.functional.normalize(u, dim=-1)
    t, _, _ = P.intersect_scene(1.01 * P.SCENE_RADIUS * u - 4 * d, d)
    assert torch.isinf(t).all()


# ---- materials and shading ----

LIGHT = torch.nn.functional.normalize(torch.tensor(P.LIGHT_DIRECTION, dtype=F64), dim=0)


def test_highlight_depends_on_the_view():
    # Normal towards the light: seen from the light, h = n, n.l = 1 and rgb = albedo + k_s (clipped);
    # seen 60 degrees away, n.h = cos(30 deg): rgb = albedo + k_s cos(30 deg)^p.
    normal, albedo = LIGHT, torch.tensor([0.75, 0.08, 0.08], dtype=F64)
    axis = torch.nn.functional.normalize(torch.linalg.cross(LIGHT, torch.tensor([0.0, 0, 1], dtype=F64), dim=0), dim=0)
    away = math.cos(math.pi / 3) * LIGHT + math.sin(math.pi / 3) * torch.linalg.cross(axis, LIGHT, dim=0)
    k_s = torch.tensor(P.SPECULAR[1], dtype=F64)
    facing, aside = (P.shade(normal, v, albedo, k_s) for v in (LIGHT, away))
    torch.testing.assert_close(facing, (albedo + k_s).clamp(max=1))
    torch.testing.assert_close(aside, albedo + k_s * math.cos(math.pi / 6) ** P.SHININESS)
    assert (facing[1:] - aside[1:] > 0.5).all()  # a white highlight on green and blue
    torch.testing.assert_close(P.shade(normal, away, albedo, k_s * 0), albedo)  # n.l = 1: fully lit


def test_each_surface_has_its_own_highlight_strength():
    # From the light, looking along -n at the point of each sphere whose normal points at the light:
    # the colour is the albedo plus that sphere's k_s, clipped to 1.
    for (centre, radius, *_), k_s in ((P.GLOSSY, P.SPECULAR[1]), (P.STRIPED, P.SPECULAR[2])):
        point = torch.tensor(centre, dtype=F64) + radius * LIGHT
        rgb, hit = P.trace((point + 2 * LIGHT)[None], -LIGHT[None])
        _, _, index = P.intersect_scene((point + 2 * LIGHT)[None], -LIGHT[None])
        albedo = P.albedo(point[None], LIGHT[None], index)
        assert hit.item()
        torch.testing.assert_close(rgb, (albedo + k_s).clamp(max=1))


def test_objects_seen_from_above_have_their_albedo():
    # Straight down onto a rod's top (normal +z, no highlight): rgb = albedo (A + (1 - A) l_z).
    lit = P.AMBIENT + (1 - P.AMBIENT) * LIGHT[2].item()
    for (x, y), *_, colour in P.RODS:
        rgb, hit = P.trace(*ray((x, y, 3), (0, 0, -1)))
        assert hit.item() and rgb[0].tolist() == pytest.approx([lit * c for c in colour])
    # The glossy sphere's top adds its highlight: k_s (n.h)^p with n = v = +z, h = unit(l + z).
    (x, y, z), radius, colour = P.GLOSSY
    rgb, _ = P.trace(*ray((x, y, 3), (0, 0, -1)))
    n_dot_h = torch.nn.functional.normalize(LIGHT + torch.tensor([0.0, 0, 1], dtype=F64), dim=0)[2].item()
    highlight = P.SPECULAR[1] * n_dot_h**P.SHININESS
    assert rgb[0].tolist() == pytest.approx([min(lit * c + highlight, 1.0) for c in colour])


def test_slab_checker_alternates_every_square():
    # Straight down onto the centres of the squares of the top face: where the slab is the first
    # hit, side-by-side squares differ in colour and diagonal neighbours match.
    s = P.CHECKER_SIZE
    k = s * (torch.arange(-8, 8, dtype=F64) + 0.5)
    x, y = torch.meshgrid(k, k, indexing="ij")
    origins = torch.stack([x, y, torch.full_like(x, 3.0)], -1)
    directions = torch.tensor([0, 0, -1.0], dtype=F64).expand_as(origins)
    rgb, hit = P.trace(origins, directions)
    slab = hit & (P.intersect_scene(origins, directions)[2] == 0)
    side = slab[1:] & slab[:-1]
    diagonal = slab[1:, 1:] & slab[:-1, :-1]
    assert side.sum() > 20 and diagonal.sum() > 20
    assert not torch.isclose(rgb[1:], rgb[:-1]).all(-1)[side].any()
    torch.testing.assert_close(rgb[1:, 1:][diagonal], rgb[:-1, :-1][diagonal])


# ---- cameras ----

SPLITS = {"train": 40, "val": 10, "test": 20}


@pytest.mark.parametrize("split, n", SPLITS.items())
def test_cameras_look_at_the_origin_from_radius_4(split, n):
    c2w = P.scene_cameras(split, n)
    assert c2w.shape == (n, 4, 4) and c2w.dtype == F64
    eye, rotation = c2w[:, :3, 3], c2w[:, :3, :3]
    torch.testing.assert_close(eye.norm(dim=-1), torch.full((n,), 4.0, dtype=F64))
    torch.testing.assert_close(-rotation[:, :, 2], -eye / 4)  # optical axis -z points at the origin
    torch.testing.assert_close(rotation.transpose(1, 2) @ rotation, torch.eye(3, dtype=F64).expand(n, 3, 3))
    torch.testing.assert_close(torch.linalg.det(rotation), torch.ones(n, dtype=F64))
    torch.testing.assert_close(c2w[:, 3], torch.tensor([0, 0, 0, 1.0], dtype=F64).expand(n, 4))
    elevation = torch.rad2deg(torch.asin(eye[:, 2] / 4))
    if split == "train":
        assert elevation.min() >= 5 and elevation.max() <= 80 and elevation.max() - elevation.min() > 60
    else:
        torch.testing.assert_close(elevation, torch.full((n,), 30.0, dtype=F64))


def test_camera_centres_are_distinct_across_splits():
    eyes = torch.cat([P.scene_cameras(split, n)[:, :3, 3] for split, n in SPLITS.items()])
    distances = torch.cdist(eyes, eyes) + torch.eye(len(eyes), dtype=F64) * 10
    assert distances.min() > 0.05


def test_unknown_split_is_named():
    with pytest.raises(ValueError, match="'training'"):
        P.scene_cameras("training", 3)


# ---- rendering ----

def test_render_is_deterministic():
    c2w = P.scene_cameras("val", 2)
    assert torch.equal(render(c2w, 24), render(c2w, 24))


def test_centre_is_opaque_and_corners_are_background():
    size, c2w = 32, torch.cat([P.scene_cameras(split, 4) for split in SPLITS])
    # The origin lies inside the glossy sphere (|centre| = 0.15 < radius 0.45) and the sub-pixel
    # rays of the four central pixels pass within 2 px (4 * 2 / focal ~ 0.18) of it: all hit.
    centre, radius, _ = P.GLOSSY
    assert math.dist(centre, (0, 0, 0)) + 4 * 2 / focal_from_fov(size, P.CAMERA_ANGLE_X) < radius
    # The corner rays pass farther than SCENE_RADIUS from the origin: they miss everything.
    corner = pixel_rays(pixel_grid(2 * size, 2 * size, dtype=F64), lens(2 * size))[0, 0]
    assert 4 * math.sin(math.acos(-corner[2].item())) > P.SCENE_RADIUS
    alpha = render(c2w, size)[..., 3]
    assert (alpha[:, size // 2 - 1:size // 2 + 1, size // 2 - 1:size // 2 + 1] == 1).all()
    assert (alpha[:, [0, 0, -1, -1], [0, -1, 0, -1]] == 0).all()


def test_alpha_is_binary_except_at_edges():
    rgba = render(P.scene_cameras("train", 6), 48, supersample=2)
    alpha, rgb = rgba[..., 3], rgba[..., :3]
    assert torch.equal(alpha * 4, torch.round(alpha * 4))  # a count of covered sub-pixels
    fractional = ((alpha > 0) & (alpha < 1)).float().mean()
    assert 0 < fractional < 0.1 and (alpha == 1).float().mean() > 0.1
    assert (rgb[alpha == 0] == 0).all() and rgb.min() >= 0 and rgb.max() <= 1


@pytest.mark.parametrize("distorted", [False, True], ids=["pinhole", "distorted-off-centre"])
def test_supersampling_averages_the_finer_render(distorted):
    c2w, size, s = P.scene_cameras("test", 2), 16, 2
    focal = focal_from_fov(size, P.CAMERA_ANGLE_X)
    # (fx, fy, cx, cy) of the coarse pixels; the fine image's pixels are s times smaller: all of them times s
    params = torch.tensor([focal, 1.1 * focal, 7.0, 9.5] if distorted else [focal, focal, 8.0, 8.0], dtype=F64)
    distortion = distortion_vector({"k1": -0.1, "p2": 0.01} if distorted else {})
    coarse = P.render_rgba(c2w, size, size, Intrinsics(params, distortion, torch.tensor(False)), supersample=s)
    fine_lens = Intrinsics(s * params, distortion, torch.tensor(False))
    fine = P.render_rgba(c2w, s * size, s * size, fine_lens, supersample=1)  # same rays, one per pixel
    blocks = lambda x: x.reshape(2, size, s, size, s, -1).mean((2, 4))  # noqa: E731
    premultiplied = lambda x: x[..., :3] * x[..., 3:]  # noqa: E731
    torch.testing.assert_close(coarse[..., 3:], blocks(fine[..., 3:]))
    torch.testing.assert_close(premultiplied(coarse), blocks(premultiplied(fine)))


def test_load_procedural_views():
    views = P.load_procedural("val", 3, 20, 30, supersample=1)
    assert views.rgba.shape == (3, 20, 30, 4) and views.rgba.dtype == torch.float32
    assert views.c2w.dtype == torch.float32 and torch.equal(views.c2w, P.scene_cameras("val", 3).float())
    focal = 15 / math.tan(0.5 * P.CAMERA_ANGLE_X)
    torch.testing.assert_close(views.intrinsics.params, torch.tensor([[focal, focal, 15.0, 10.0]] * 3, dtype=F64))
    assert not views.intrinsics.is_distorted().any()


def ray_meets_box(origins: torch.Tensor, directions: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    """Whether rays [..., 3] pass through the box [2, 3] in front of their origins (slab test): [...]."""
    t0, t1 = (box[0] - origins) / directions, (box[1] - origins) / directions
    t_in, t_out = torch.minimum(t0, t1).amax(-1), torch.maximum(t0, t1).amin(-1)
    return (t_in <= t_out) & (t_out > 0)


def test_every_pixel_that_shows_an_object_has_its_ray_through_the_scenes_box():
    # the ground truth's partly covered edge pixels: their rays (through pixel centres) can miss the
    # objects themselves, yet the field must absorb there, so the grid's box must hold those rays' paths
    scene = ProceduralScene(image_size=64, n_test=8)
    views = scene.views("test")
    shown = views.rgba[..., 3] > 0  # [N, H, W]: some object in the pixel
    rays = [camera_rays(c2w, views.height, views.width, views.intrinsics[k]) for k, c2w in enumerate(views.c2w)]
    origins, directions = (torch.stack(r).double() for r in zip(*rays))
    assert ray_meets_box(origins, directions, scene.bounding_box().double())[shown].all()
    assert not ray_meets_box(origins, directions, objects_box().double())[shown].all()  # the exact box cuts some


def test_signed_distances_vanish_where_rays_hit_and_change_sign_across_the_surface():
    # the scene's distances (signed_distances) against its ray intersections (intersect_scene): two
    # formulas of the same shapes, on every pixel ray of two views
    c2w = scene_cameras("test", 2)
    origins, directions = camera_rays(c2w, 48, 48, lens(48))
    origins, directions = origins.double().reshape(-1, 3), directions.double().reshape(-1, 3)
    t, normal, index = intersect_scene(origins, directions)
    hit = torch.isfinite(t)
    assert 500 < hit.sum() < len(t)
    points, normal = origins[hit] + t[hit, None] * directions[hit], normal[hit]
    distances = signed_distances(points)  # [N, K]
    assert distances.amin(-1).abs().max() < 1e-9  # on the surface
    # outside a little along the outward normal, inside a little against it
    assert (signed_distances(points + 1e-4 * normal).amin(-1) > 0).all()
    assert (signed_distances(points - 1e-4 * normal).amin(-1) < 0).all()
    nearest = distances.abs().argmin(-1)
    assert (nearest == index[hit]).float().mean() > 0.99  # the object hit (ties where objects touch)
    ts = torch.linspace(NEAR, FAR, 200, dtype=torch.float64)
    missed = origins[~hit, None] + ts[:, None] * directions[~hit, None]  # [M, 200, 3]
    assert (signed_distances(missed).amin(-1) > 0).all()
