"""The glossy scene: the torus against hand-worked hits and a float64 brute-force march, reflections
against the reflection formula worked by hand, transparency, ranges, and ``nerfexp-scene --scene glossy``."""

import math

import pytest
import torch

from nerfexp.commands import scene
from nerfexp.data import glossy as G
from nerfexp.data.blender import BlenderScene
from nerfexp.data.procedural import CAMERA_ANGLE_X, scene_cameras, shade
from nerfexp.geometry.cameras import camera_rays, focal_from_fov
from nerfexp.geometry.lenses import Intrinsics

F64 = torch.float64


def ray(origin, direction):
    d = torch.tensor(direction, dtype=F64)
    return torch.tensor(origin, dtype=F64)[None], (d / d.norm())[None]


def unit(v):
    return v / v.norm(dim=-1, keepdim=True)


def torus_implicit(points, centre, major, minor, axis):
    """(rho - R)^2 + z^2 - r^2 [...] at points [..., 3], with z along and rho away from the unit axis."""
    q = points - torch.tensor(centre, dtype=F64)
    a = unit(torch.tensor(axis, dtype=F64))
    z = (q * a).sum(-1)
    rho = (q - z[..., None] * a).norm(dim=-1)
    return (rho - major) ** 2 + z**2 - minor**2


# ---- the torus, against hand-worked hits ----

# A torus around z at the origin with R = 1, r = 0.25 unless the case says otherwise.
@pytest.mark.parametrize("origin, direction, centre, axis, t, normal", [
    ((3, 0, 0), (-1, 0, 0), (0, 0, 0), (0, 0, 1), 3 - 1.25, (1, 0, 0)),  # outer rim: distance - (R + r)
    ((0, -4, 0), (0, 1, 0), (0, 0, 0), (0, 0, 1), 4 - 1.25, (0, -1, 0)),
    ((1, 0, 2), (0, 0, -1), (0, 0, 0), (0, 0, 1), 2 - 0.25, (0, 0, 1)),  # onto the top of the tube
    ((0, 0, 0), (1, 0, 0), (0, 0, 0), (0, 0, 1), 1 - 0.25, (-1, 0, 0)),  # from the hole: the inner side
    # 45 degrees down through the centre circle's point (1, 0, 0): the ray (-1 + s, 0, 2 - s), s = t / sqrt 2,
    # is sqrt 2 |2 - s| from it (perpendicular to the circle there), so it enters at s = 2 - 0.25 / sqrt 2
    ((-1, 0, 2), (1, 0, -1), (0, 0, 0), (0, 0, 1), 2 * math.sqrt(2) - 0.25, (-math.sqrt(0.5), 0, math.sqrt(0.5))),
    ((1, 2, 6), (0, 0, -1), (1, 2, 3), (1, 0, 0), 3 - 1.25, (0, 0, 1)),  # axis x, shifted: the ring is in y-z
])
def test_torus_hits_match_hand_worked(origin, direction, centre, axis, t, normal):
    t_hit, n_hit = G.intersect_torus(*ray(origin, direction), centre, 1.0, 0.25, axis)
    torch.testing.assert_close(t_hit, torch.tensor([t], dtype=F64), atol=1e-9, rtol=0)
    torch.testing.assert_close(n_hit, torch.tensor([normal], dtype=F64), atol=1e-9, rtol=0)


@pytest.mark.parametrize("origin, direction, centre, axis", [
    ((0, 0, 3), (0, 0, -1), (0, 0, 0), (0, 0, 1)),  # along the axis, through the hole
    ((0.5, 0.3, -3), (0, 0, 1), (0, 0, 0), (0, 0, 1)),  # parallel to the axis, inside the hole (0.58 < 0.75)
    ((3, 0, 0.26), (-1, 0, 0), (0, 0, 0), (0, 0, 1)),  # horizontal, just above the tube (z = 0.26 > r)
    ((3, 0, 0), (1, 0, 0), (0, 0, 0), (0, 0, 1)),  # pointing away
    ((4, 2, 3), (-1, 0, 0), (1, 2, 3), (1, 0, 0)),  # along a shifted x axis, through the hole
])
def test_torus_misses_are_inf_with_zero_normal(origin, direction, centre, axis):
    t, n = G.intersect_torus(*ray(origin, direction), centre, 1.0, 0.25, axis)
    assert t.item() == math.inf and n.abs().sum().item() == 0


def test_torus_random_rays_match_a_float64_brute_force_march():
    # The scene's tilted torus; rays from 2.5 away aimed at random points of its bounding ball, so that
    # about half hit. Reference: the first sign change of the implicit function on a 5e-4 grid, then bisection.
    g = torch.Generator().manual_seed(0)
    centre, R, r, axis = G.TORUS_CENTRE, G.TORUS_MAJOR, G.TORUS_MINOR, G.TORUS_AXIS
    c = torch.tensor(centre, dtype=F64)
    origins = c + 2.5 * unit(torch.randn(300, 3, generator=g, dtype=F64))
    offsets = torch.rand(300, 1, generator=g, dtype=F64) * unit(torch.randn(300, 3, generator=g, dtype=F64))
    targets = c + (R + r) * offsets
    directions = unit(targets - origins)
    t, normal = G.intersect_torus(origins, directions, centre, R, r, axis)

    grid = torch.arange(0, 5, 5e-4, dtype=F64)  # [S]
    f = torus_implicit(origins[:, None] + grid[:, None] * directions[:, None], centre, R, r, axis)  # [N, S]
    inside = f <= 0
    hit = inside.any(-1)
    first = inside.float().argmax(-1)  # the first sample inside
    lo, hi = grid[(first - 1).clamp_min(0)], grid[first]
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        mid_inside = torus_implicit(origins + mid[:, None] * directions, centre, R, r, axis) <= 0
        lo, hi = torch.where(mid_inside, lo, mid), torch.where(mid_inside, mid, hi)

    assert 0.3 < hit.double().mean() < 0.9  # both cases are exercised
    assert torch.equal(torch.isfinite(t), hit)
    torch.testing.assert_close(t[hit], hi[hit], atol=1e-7, rtol=0)  # no closer root: the first one
    points = origins[hit] + t[hit, None] * directions[hit]
    assert torus_implicit(points, centre, R, r, axis).abs().max() < 1e-4
    gradient = torch.func.vmap(torch.func.grad(lambda p: torus_implicit(p, centre, R, r, axis)))(points)
    torch.testing.assert_close(normal[hit], unit(gradient), atol=1e-6, rtol=0)
    assert (normal[~hit] == 0).all()


# ---- the scene ----


def test_objects_fit_in_the_scene_ball():
    # base: its bottom rim; mirror: |centre| + radius; torus: |centre| + R + r (a loose bound)
    (bx, by), base_radius, bottom, _ = G.BASE
    extents = [math.hypot(math.hypot(bx, by) + base_radius, bottom),
               math.dist(G.MIRROR[0], (0, 0, 0)) + G.MIRROR[1],
               math.dist(G.TORUS_CENTRE, (0, 0, 0)) + G.TORUS_MAJOR + G.TORUS_MINOR]
    assert max(extents) <= G.SCENE_RADIUS < 1.5  # and so inside Blender's [-1.5, 1.5]^3


def test_environment_is_finite_in_range_and_structured():
    directions = unit(torch.randn(4096, 3, generator=torch.Generator().manual_seed(1), dtype=F64))
    rgb = G.environment(directions)
    assert rgb.shape == (4096, 3) and torch.isfinite(rgb).all()
    assert rgb.min() >= 0 and rgb.max() <= 1
    assert rgb.std(0).min() > 0.05  # not a flat colour: reflections carry structure
    up, down = G.environment(torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]], dtype=F64))
    torch.testing.assert_close(up, torch.tensor(G.SKY_ZENITH, dtype=F64))  # the gradient's ends
    torch.testing.assert_close(down, torch.tensor(G.GROUND_NADIR, dtype=F64))


def test_mirror_pixels_show_the_tinted_environment_in_the_reflected_direction():
    # The highest training camera looks down on the mirror sphere. A sub-pixel ray that hits the sphere
    # above every other object (the torus's top is at centre + r + R sin(tilt)) and reflects upwards
    # leaves the scene: its pixel is F tint environment(r), r = d - 2 (d.n) n, F = F0 + (1 - F0) (1 - cos)^5.
    c2w = scene_cameras("train", 100)[-1:]
    size = 32
    lens = Intrinsics.pinhole(focal_from_fov(size, CAMERA_ANGLE_X), size, size)
    image = G.render_glossy_rgba(c2w, size, size, lens, supersample=1)[0]  # [H, W, 4]
    origins, directions = (x[0].reshape(-1, 3) for x in camera_rays(c2w, size, size, lens))
    centre, radius = torch.tensor(G.MIRROR[0], dtype=F64), G.MIRROR[1]
    q = origins - centre
    b = (q * directions).sum(-1)
    disc = b**2 - (q * q).sum(-1) + radius**2
    t = -b - disc.clamp_min(0).sqrt()
    n = (q + t[:, None] * directions) / radius
    z_hit = (origins + t[:, None] * directions)[:, 2]
    r = directions - 2 * (directions * n).sum(-1, keepdim=True) * n
    torus_top = G.TORUS_CENTRE[2] + G.TORUS_MINOR + G.TORUS_MAJOR * math.sin(G.TORUS_TILT)
    chosen = (disc > 0) & (z_hit > torus_top) & (r[:, 2] > 0)
    assert chosen.sum() >= 10
    cos = (-directions * n).sum(-1, keepdim=True)
    fresnel = G.F0[1] + (1 - G.F0[1]) * (1 - cos) ** 5
    expected = fresnel * torch.tensor(G.MIRROR_TINT, dtype=F64) * G.environment(r)
    torch.testing.assert_close(image.reshape(-1, 4)[chosen, :3].double(), expected[chosen], atol=1e-6, rtol=0)
    torch.testing.assert_close(image.reshape(-1, 4)[chosen, 3], torch.ones(int(chosen.sum())))


@pytest.mark.parametrize("bounces", [0, 1, 2])
def test_clear_coat_reflects_the_mirror_up_to_the_bounce_limit(bounces):
    # In the plane x = -0.3 (through the mirror's centre; no point of the torus is that far from its
    # centre's x = 0.4, as R + r < 0.7) a ray comes down onto the base's top at P = (-0.3, 0.45, -0.5)
    # along d = unit(0, -0.75, -0.6) and reflects to r1 = unit(0, -0.75, 0.6), towards the mirror's upper
    # front. Checker at P: floor((P - 0.08 z) / 0.16) = (-2, 2, -4), even sum: the first colour.
    # rgb = (1 - F_b) diffuse + F_b L, F_b with cos = 0.6 / |(0.75, 0.6)|; L = environment(r1) with no
    # bounce, else the mirror's F_m tint environment(r2), r2 reflected off the sphere, leaving upwards
    # (the reflected ray starts SURFACE_OFFSET above P).
    p = torch.tensor([-0.3, 0.45, -0.5], dtype=F64)
    d = unit(torch.tensor([0.0, -0.75, -0.6], dtype=F64))
    r1 = d * torch.tensor([1.0, 1.0, -1.0], dtype=F64)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    cos_b = 0.6 / math.hypot(0.75, 0.6)
    f_b = G.F0[0] + (1 - G.F0[0]) * (1 - cos_b) ** 5
    diffuse = shade(up, -d, torch.tensor(G.BASE_COLOURS[0], dtype=F64), torch.tensor(0.0, dtype=F64))
    if bounces == 0:
        incoming = G.environment(r1)
    else:
        q = p + G.SURFACE_OFFSET * up - torch.tensor(G.MIRROR[0], dtype=F64)  # the secondary ray's origin
        b = (q * r1).sum()
        s = -b - torch.sqrt(b**2 - (q * q).sum() + G.MIRROR[1] ** 2)
        n = (q + s * r1) / G.MIRROR[1]
        r2 = r1 - 2 * (r1 * n).sum() * n
        assert r2[2] > 0 and r2[0] == 0  # up, in the plane x = -0.3: it leaves the scene
        f_m = G.F0[1] + (1 - G.F0[1]) * (1 + (r1 * n).sum()) ** 5
        incoming = f_m * torch.tensor(G.MIRROR_TINT, dtype=F64) * G.environment(r2)
    expected = (1 - f_b) * diffuse + f_b * incoming
    rgb, alpha = G.trace_glossy((p - 3 * d)[None], d[None], bounces)
    torch.testing.assert_close(rgb[0], expected, atol=1e-9, rtol=0)
    assert alpha.item() == 1


def test_torus_top_reflects_the_zenith_with_a_highlight():
    # The tilted torus's highest point: the ring's highest direction u = unit(z - (z.a) a), then up by r;
    # the normal there is z. A ray straight down onto it meets nothing else and reflects straight up, to
    # the sky's zenith colour: rgb = (1 - F0) diffuse + F0 zenith + k_s (n.h)^P, h = unit(l + z) (n.l > 0).
    a = unit(torch.tensor(G.TORUS_AXIS, dtype=F64))
    z = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    top = torch.tensor(G.TORUS_CENTRE, dtype=F64) + G.TORUS_MAJOR * unit(z - a[2] * a) + G.TORUS_MINOR * z
    origin, down = top + 2 * z, -z
    t, normal = G.intersect_torus(origin[None], down[None], G.TORUS_CENTRE, G.TORUS_MAJOR, G.TORUS_MINOR,
                                  G.TORUS_AXIS)
    torch.testing.assert_close(t, torch.tensor([2.0], dtype=F64), atol=1e-9, rtol=0)
    torch.testing.assert_close(normal[0], z, atol=1e-6, rtol=0)
    light = unit(torch.tensor(G.LIGHT_DIRECTION, dtype=F64))
    diffuse = shade(z, z, torch.tensor(G.TORUS_COLOUR, dtype=F64), torch.tensor(0.0, dtype=F64))
    highlight = G.SPECULAR[2] * (unit(light + z)[2]) ** G.SHININESS
    expected = (1 - G.F0[2]) * diffuse + G.F0[2] * torch.tensor(G.SKY_ZENITH, dtype=F64) + highlight
    rgb, alpha = G.trace_glossy(origin[None], down[None])
    torch.testing.assert_close(rgb[0], expected.clamp(0, 1), atol=1e-9, rtol=0)
    assert alpha.item() == 1


def test_rays_that_miss_are_transparent_and_images_are_finite_in_range():
    rgb, alpha = G.trace_glossy(*ray((0, 0, 4), (0, 0, 1)))  # straight up, away from everything
    assert alpha.item() == 0 and rgb.abs().sum().item() == 0
    c2w = scene_cameras("val", 2)
    size = 24
    focal = focal_from_fov(size, CAMERA_ANGLE_X)
    lens = Intrinsics.pinhole(focal, size, size)
    images = G.render_glossy_rgba(c2w, size, size, lens, supersample=2)
    assert images.shape == (2, size, size, 4) and torch.isfinite(images).all()
    assert images.min() >= 0 and images.max() <= 1
    # Every sub-pixel ray of a pixel passes farther than SCENE_RADIUS from the origin: the pixel is empty.
    origins, directions = camera_rays(c2w, 2 * size, 2 * size, Intrinsics.pinhole(2 * focal, 2 * size, 2 * size))
    distance = torch.linalg.cross(-origins, directions, dim=-1).norm(dim=-1)  # from the origin to the ray
    far = (distance > G.SCENE_RADIUS).reshape(2, size, 2, size, 2).all(-1).all(-2)
    assert far.any() and (~far).any()
    assert (images[far] == 0).all()
    assert torch.equal(images, G.render_glossy_rgba(c2w, size, size, lens, supersample=2))  # deterministic


def test_nerfexp_scene_glossy_writes_a_blender_dataset(tmp_path):
    scene.main([str(tmp_path), "--scene", "glossy", "--resolution", "16", "--n-train", "3", "--n-val", "1",
                "--n-test", "1"])
    for split, n in (("train", 3), ("val", 1), ("test", 1)):
        assert len(list((tmp_path / split).glob("*.png"))) == n
    loaded = BlenderScene(root=str(tmp_path))
    assert len(loaded.views("train")) == 3
    views, rendered = loaded.views("test"), G.load_glossy("test", 1, 16, 16)
    # 8-bit rounding: half a level, and float32's error where alpha is k / 4 and 255 k / 4 ends in .5
    torch.testing.assert_close(views.rgba, rendered.rgba, atol=0.5 / 255 + 1e-6, rtol=0)
    torch.testing.assert_close(views.c2w, rendered.c2w)
    assert rendered.rgba[..., 3].max() == 1 and rendered.rgba[..., 3].min() == 0  # the scene, and empty space
