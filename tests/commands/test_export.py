"""``nerfexp-export``: the mesh of the built-in scene's true geometry against its surface, points from the
scene's exact depths on its surface, the box and network chosen, the command line on a trained run, and
bad input."""

import json
import math
import re
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree
from torch import Tensor, nn

from nerfexp import manifest
from nerfexp.commands import export
from nerfexp.commands.export import DENSITY_LIMIT, build_parser, main, trained_run
from nerfexp.data.procedural import (
    CAMERA_ANGLE_X,
    FAR,
    GLOSSY,
    NEAR,
    RODS,
    SLAB,
    STRIPED,
    ProceduralScene,
    intersect_scene,
    objects_box,
    scene_cameras,
    signed_distances,
)
from nerfexp.data.views import Views
from nerfexp.errors import NerfexpError
from nerfexp.geometry.cameras import camera_rays, focal_from_fov
from nerfexp.geometry.lenses import Intrinsics
from nerfexp.nerf.fields import FieldOutputs
from nerfexp.nerf.hierarchy import HierarchyChoice
from nerfexp.nerf.occupancy import OccupancyGrid
from nerfexp.nerf.volume_renderer import VolumeRenderer
from nerfexp.pixels import to_uint8
from nerfexp.products.mesh import (
    THRESHOLD_QUANTILE,
    export_box,
    extract_mesh,
    field_threshold,
    final_field,
    view_points,
)
from tests.helpers import crossed_threshold, digests, read_ply, run_nerfexp, threshold_between, undocumented_arguments

F64 = torch.float64
THRESHOLD = 50.0  # nerfexp-export's default
RAMP = 0.05  # the test field's density falls from THRESHOLD to 0 over this distance outside an object
RESOLUTION = 64


def object_distances(points: Tensor) -> Tensor:
    """[N, K]: the signed distance of points [N, 3] to each of the built-in scene's objects, in float64."""
    return signed_distances(points.double())


class BuiltInSceneField(nn.Module):
    """The built-in scene's objects as a field whose density crosses ``THRESHOLD`` exactly on their surface:
    THRESHOLD (1 - s / ``RAMP``), 0 from ``RAMP`` outside, where s is the signed distance to the nearest
    object; colour (1 + direction) / 2, so that an exported colour tells the direction the vertex was seen
    along. Linear in s across the surface, as marching cubes assumes between grid points, so a vertex can
    be held to a small fraction of a cell: a shifted or scaled grid would fail by a whole one."""

    def density(self, positions: Tensor) -> Tensor:
        distance = object_distances(positions).amin(-1)
        return (THRESHOLD * (1 - distance / RAMP)).clamp_min(0).to(positions.dtype)

    def forward(self, positions: Tensor, directions: Tensor) -> FieldOutputs:
        return FieldOutputs(rgb=(1 + directions) / 2, sigma=self.density(positions))


def true_surface(spacing: float) -> np.ndarray:
    """Points [M, 3] about ``spacing`` apart on the boundary of the union of the objects: samples of each
    object's surface that lie outside every other object (not inside, not on its surface)."""
    def grid(lo: float, hi: float) -> Tensor:
        return torch.linspace(lo, hi, math.ceil((hi - lo) / spacing) + 1, dtype=F64)

    def disc(centre_xy, radius: float, z: float) -> Tensor:
        rings = [(rho, max(1, math.ceil(2 * math.pi * rho / spacing))) for rho in grid(0, radius).tolist()]
        angles = torch.cat([torch.arange(n, dtype=F64) * 2 * math.pi / n for _, n in rings])
        rho = torch.cat([torch.full((n,), r, dtype=F64) for r, n in rings])
        return torch.stack([centre_xy[0] + rho * angles.cos(), centre_xy[1] + rho * angles.sin(),
                            torch.full_like(rho, z)], -1)

    def sphere(centre, radius: float) -> Tensor:  # a Fibonacci lattice
        n = math.ceil(4 * math.pi * radius**2 / spacing**2)
        k = torch.arange(n, dtype=F64) + 0.5
        z, phi = 1 - 2 * k / n, k * math.pi * (3 - math.sqrt(5))
        unit = torch.stack([(1 - z**2).sqrt() * phi.cos(), (1 - z**2).sqrt() * phi.sin(), z], -1)
        return torch.tensor(centre, dtype=F64) + radius * unit

    lower, upper = SLAB
    slab = []
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        for side in (lower[axis], upper[axis]):
            face = torch.stack(torch.meshgrid(grid(lower[u], upper[u]), grid(lower[v], upper[v]), indexing="ij"), -1)
            point = torch.empty(*face.shape[:2], 3, dtype=F64)
            point[..., u], point[..., v], point[..., axis] = face[..., 0], face[..., 1], side
            slab.append(point.reshape(-1, 3))
    surfaces = [torch.cat(slab), sphere(*GLOSSY[:2]), sphere(*STRIPED)]
    for xy, radius, top, _ in RODS:
        bottom = SLAB[1][2]
        angle = torch.arange(math.ceil(2 * math.pi * radius / spacing), dtype=F64)
        angle = angle * 2 * math.pi / len(angle)
        side = torch.stack(torch.meshgrid(angle, grid(bottom, top), indexing="ij"), -1).reshape(-1, 2)
        side = torch.stack([xy[0] + radius * side[:, 0].cos(), xy[1] + radius * side[:, 0].sin(), side[:, 1]], -1)
        surfaces.append(torch.cat([side, disc(xy, radius, top), disc(xy, radius, bottom)]))
    kept = []
    for index, points in enumerate(surfaces):
        others = torch.cat([object_distances(points)[:, :index], object_distances(points)[:, index + 1:]], 1)
        kept.append(points[(others > 1e-9).all(1)])
    return torch.cat(kept).numpy()


def test_the_mesh_of_the_built_in_scenes_true_geometry_lies_on_its_surface_and_covers_it():
    # the objects' box with 0.04 of room (the scene's own, [-1.5, 1.5]^3, at about twice the resolution: as fine
    # cells at an eighth of the points), whose grid planes miss the slab's faces (on a plane, a face is a tie)
    box = objects_box().double() + torch.tensor([[-0.04], [0.04]], dtype=torch.float64)
    cell = ((box[1] - box[0]).max() / RESOLUTION).item()  # the grid's spacing (the other edges' within 4%)
    mesh, colours = extract_mesh(BuiltInSceneField(), box, RESOLUTION, THRESHOLD, batch=50_000, device="cpu")
    surface = true_surface(cell / 8)

    # every vertex lies within 0.4 cells of the true surface, most on it; every point of that surface
    # farther than a cell from any other object lies within a cell of a vertex. Nearer, in the crevices
    # where the spheres rest on the slab and at the rods' feet, the gap is narrower than a cell and the
    # grid bridges it (the figures of docs/export.md)
    vertex_error = object_distances(torch.from_numpy(mesh.vertices)).amin(-1).abs().numpy() / cell
    assert vertex_error.max() < 0.4 and np.median(vertex_error) < 0.01, np.quantile(vertex_error, [0.5, 1])
    second_nearest = object_distances(torch.from_numpy(surface)).sort(-1).values[:, 1].numpy()
    open_surface = surface[second_nearest > cell]
    assert len(open_surface) > 0.95 * len(surface)
    to_mesh, _ = cKDTree(mesh.vertices).query(open_surface)
    assert to_mesh.max() <= cell, (to_mesh.max() / cell, np.median(to_mesh) / cell)

    # normals point out of the objects: on the glossy sphere, away from its centre
    centre, radius, _ = GLOSSY
    offsets = mesh.vertices - np.array(centre)
    on_sphere = np.abs(np.linalg.norm(offsets, axis=1) - radius) < cell
    on_sphere &= mesh.vertices[:, 2] > SLAB[1][2] + 2 * cell  # away from where the sphere meets the slab
    radial = offsets[on_sphere] / np.linalg.norm(offsets[on_sphere], axis=1, keepdims=True)
    cosines = (mesh.normals[on_sphere] * radial).sum(1)
    assert on_sphere.sum() > 1000 and cosines.min() > 0 and np.median(cosines) > 0.95, np.quantile(cosines, [0, 0.5])

    # each vertex is coloured by the field seen along its inward normal: (1 - normal) / 2 here
    expected = to_uint8(torch.from_numpy((1 - mesh.normals) / 2))
    assert colours.dtype == np.uint8 and colours.shape == mesh.vertices.shape
    assert np.abs(colours.astype(int) - expected.astype(int)).max() <= 1


def test_the_grid_is_evaluated_in_batches_to_the_same_mesh():
    box = torch.tensor([[-0.8, -0.8, -0.7], [0.8, 0.8, 0.6]], dtype=F64)
    whole, whole_colours = extract_mesh(BuiltInSceneField(), box, 16, THRESHOLD, batch=10**6, device="cpu")
    parts, parts_colours = extract_mesh(BuiltInSceneField(), box, 16, THRESHOLD, batch=97, device="cpu")
    assert np.array_equal(whole.vertices, parts.vertices) and np.array_equal(whole.faces, parts.faces)
    assert np.array_equal(whole_colours, parts_colours)


OPACITY = 0.8  # what the stand-in renderer's rays absorb where they hit an object other than a rod
COLOUR = (0.2, 0.5, 0.7)


class ExactModule:
    """Stands in for a trained ``NeRFModule`` in ``view_points``: renders the built-in scene with its exact
    depths (``intersect_scene``). A ray that hits a rod absorbs 0.3 of the light, any other hit ``OPACITY``,
    in ``COLOUR``, over a white background."""

    device = torch.device("cpu")
    renderer = SimpleNamespace(background=torch.ones(3))

    def render_image(self, origins: Tensor, directions: Tensor, viewdirs: Tensor | None = None) -> dict[str, Tensor]:
        t, _, index = intersect_scene(origins.double(), directions.double())
        hit = torch.isfinite(t)
        opacity = torch.where(hit, torch.where(index >= 3, 0.3, OPACITY), 0.0).float()  # [H, W]
        rgb = opacity[..., None] * torch.tensor(COLOUR) + (1 - opacity[..., None]) * self.renderer.background
        return {"rgb": rgb, "depth": torch.where(hit, t, FAR).float(), "opacity": opacity}


def test_points_from_the_scenes_exact_depths_lie_on_its_surface_in_the_absorbed_colour():
    size = 32
    lenses = Intrinsics.pinhole(focal_from_fov(size, CAMERA_ANGLE_X), size, size, (2,))
    lenses.params[1, 2:] += torch.tensor([3.0, -2.0], dtype=torch.float64)  # the second view's off the centre
    views = Views(rgba=torch.zeros(2, size, size, 4), c2w=scene_cameras("test", 2).float(), intrinsics=lenses)
    points, colours = view_points(ExactModule(), ProceduralScene(), views, min_opacity=0.5)

    # one point per pixel whose ray hits an object other than a rod (whose 0.3 is below 0.5)
    origins, directions = camera_rays(views.c2w, size, size, views.intrinsics)  # the float32 rays it renders
    t, _, index = intersect_scene(origins.double(), directions.double())
    assert len(points) == (torch.isfinite(t) & (index < 3)).sum() > 200
    # on the surface (distance 0 to the nearest object), to float32's rounding of depths near 4
    assert object_distances(points).amin(-1).abs().max() < 1e-5
    # the colour of the absorbed light: the rendered 0.8 COLOUR + 0.2 white without the white
    torch.testing.assert_close(colours, torch.tensor(COLOUR).expand_as(colours))


def renderer(grid: OccupancyGrid | None = None) -> VolumeRenderer:
    return VolumeRenderer(BuiltInSceneField, HierarchyChoice(hierarchical=True, n_coarse=4, n_fine=4, n_single=8),
                          near=NEAR, far=FAR, grid=grid)


def test_the_box_is_the_bounded_modules_else_the_scenes_and_the_field_the_fine_network():
    plain = renderer()
    assert final_field(plain) is plain.fine
    unhierarchical = VolumeRenderer(BuiltInSceneField,
                                    HierarchyChoice(hierarchical=False, n_coarse=4, n_fine=4, n_single=8),
                                    near=NEAR, far=FAR)
    assert final_field(unhierarchical) is unhierarchical.coarse
    scene = ProceduralScene()
    torch.testing.assert_close(export_box(plain, scene), scene.bounding_box().double())
    configured = ProceduralScene(aabb=[[-1, -1, -1], [1, 1, 0.5]])
    assert export_box(plain, configured).tolist() == [[-1, -1, -1], [1, 1, 0.5]]
    gridded = renderer(OccupancyGrid(aabb=[[-2, -1, -1], [2, 1, 0.25]]))
    assert export_box(gridded, configured).tolist() == [[-2, -1, -1], [2, 1, 0.25]]


@pytest.mark.slow
def test_exporting_a_trained_run_writes_a_mesh_and_points_that_read_back(tiny_run, tmp_path):
    # a threshold above every density is one line giving the densities' range; half-way up it is a surface
    too_high = run_nerfexp(str(tiny_run), "--resolution", "16", "--threshold", "1e9", cwd=tmp_path,
                           script="nerfexp-export")
    lines = too_high.stderr.strip().splitlines()
    assert too_high.returncode == 1 and len(lines) == 1, too_high.stderr[-2000:]
    assert lines[0].startswith("nerfexp-export: error: no surface at --threshold 1e+09: "), lines[0]
    threshold = threshold_between(lines[0])

    checkpoint = tiny_run / "checkpoints" / "last.ckpt"  # a checkpoint path works as a run directory does
    result = run_nerfexp(str(checkpoint), "--resolution", "16", "--threshold", f"{threshold}", "--chunk", "300",
                         new_process=True, cwd=tmp_path, script="nerfexp-export")
    assert result.returncode == 0, result.stderr[-3000:]
    summary = result.stdout.strip().splitlines()
    out = tiny_run / "export"
    assert len(summary) == 1 and summary[0].startswith("mesh.ply: ") and summary[0].endswith(f"written to {out}")
    assert sorted(p.name for p in out.iterdir()) == ["mesh.ply", "points.ply"]
    assert not list(tiny_run.glob(".export*"))  # no temporary folder left behind

    comments, mesh = read_ply((out / "mesh.ply").read_bytes())
    vertex, faces = mesh["vertex"], mesh["face"]["vertex_indices"]
    assert f"{checkpoint}" in comments[0] and len(vertex) > 0 and len(faces) > 0
    assert 0 <= faces.min() and faces.max() < len(vertex)
    xyz = np.stack([vertex[n] for n in ("x", "y", "z")], 1)
    stated = re.search(r"over the box (\[\[.*\]\])$", comments[1])  # the box the export says it meshed
    box = np.array(json.loads(stated[1]))
    assert (xyz >= box[0] - 1e-3).all() and (xyz <= box[1] + 1e-3).all()  # to its 4 stated digits
    normals = np.stack([vertex[n] for n in ("nx", "ny", "nz")], 1)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1, atol=1e-5)
    rgb = np.stack([vertex[n] for n in ("red", "green", "blue")], 1)
    assert rgb.dtype == np.uint8 and np.ptp(rgb) > 0  # in [0, 255] by its type; not one flat colour

    _, cloud = read_ply((out / "points.ply").read_bytes())
    points = cloud["vertex"]
    assert 0 < len(points) <= 2 * 24 * 24  # TINY: two test views of 24 x 24 pixels
    assert points.dtype.names == ("x", "y", "z", "red", "green", "blue") and points["red"].dtype == np.uint8
    xyz = torch.from_numpy(np.stack([points[n] for n in ("x", "y", "z")], 1)).double()
    # each point lies between near and far along a ray of one of the test cameras
    eyes = scene_cameras("test", 2)[:, :3, 3]
    distances = torch.cdist(xyz, eyes)
    assert ((distances >= NEAR - 1e-4) & (distances <= FAR + 1e-4)).any(1).all()


@pytest.mark.parametrize("make", ["nothing", "a_folder_that_is_not_a_run", "an_ndc_run"])
def test_exporting_what_is_not_a_world_space_run_is_one_clear_line(tmp_path, make):
    path = tmp_path / "run"
    expected = f"{path} does not exist"
    if make == "a_folder_that_is_not_a_run":
        path.mkdir()
        expected = f"{path} is not a run directory"
    elif make == "an_ndc_run":  # only the saved config and a checkpoint file: refused before either is read
        (path / ".hydra").mkdir(parents=True)
        (path / ".hydra" / "config.yaml").write_text(
            "data:\n  _target_: nerfexp.data.llff.LLFFScene\n  root: /nowhere\n  ndc: true\n")
        (path / "checkpoints").mkdir()
        (path / "checkpoints" / "last.ckpt").write_bytes(b"")
        expected = f"{path} was trained on NDC rays (data.ndc=true"
    with pytest.raises(SystemExit) as stop:  # the command in this process (the slow test runs its script)
        main([str(path)])
    message = str(stop.value.code)  # sys.exit(message): the message on stderr, exit status 1
    assert message.startswith("nerfexp-export: error: ") and expected in message and "\n" not in message, message
    assert not Path(path / "export").exists()


def test_the_commands_help_explains_every_option():
    parser = build_parser()
    text = " ".join(parser.format_help().split())  # argparse wraps lines
    assert parser.description and "``" not in text
    assert undocumented_arguments(build_parser) == []
    assert "absorbs 1 - exp(-sigma h) of the light" in text and "63% over 0.02" in text


def test_an_export_replaces_its_own_folder_and_refuses_one_holding_a_users_file(tiny_run, tmp_path):
    run_dir = shutil.copytree(tiny_run, tmp_path / "run", ignore=shutil.ignore_patterns("export"))
    threshold = crossed_threshold(run_dir, 4)  # a mesh on any CPU: the tiny run's default may miss so coarse a grid
    main([str(run_dir), "--resolution", "4", "--threshold", threshold])
    main([str(run_dir), "--resolution", "4", "--threshold", threshold])  # its own folder: replaced as a whole
    assert manifest.unproven(run_dir, ["export/mesh.ply", "export/points.ply"]) == []
    for name, content in (("mesh.obj", "mine"), ("mesh.ply", "a user's own mesh, in the name of an export's")):
        (run_dir / "export" / name).write_text(content)
        before = digests(run_dir / "export")
        with pytest.raises(SystemExit) as exit:
            main([str(run_dir), "--resolution", "4", "--threshold", threshold])
        assert exit.value.code == (
            f"nerfexp-export: error: {run_dir / 'export' / name} is not a file nerfexp-export wrote (it is not in "
            f"{run_dir / manifest.MANIFEST}, or changed since): move it elsewhere: nerfexp-export replaces this "
            "folder as a whole")
        assert digests(run_dir / "export") == before and not list(run_dir.glob(".export*"))
        (run_dir / "export" / name).rename(tmp_path / name)  # moved: the next one is refused alone


@pytest.mark.parametrize("given", [True, False])
def test_a_threshold_that_no_density_crosses_is_one_line_naming_it_and_the_densities(tiny_run, tmp_path, monkeypatch,
                                                                                     given):
    # above every density: given, or read from the field as a briefly trained field's default can miss a coarse
    # grid's densities, which the line names as the default (the user gave no --threshold)
    run_dir = shutil.copytree(tiny_run, tmp_path / "run", ignore=shutil.ignore_patterns("export"))
    before = digests(run_dir)
    if given:
        argv, named = ["--threshold", f"{DENSITY_LIMIT!r}"], f"--threshold {DENSITY_LIMIT:g}"
    else:
        monkeypatch.setattr(export, "field_threshold", lambda field, points, batch, device: DENSITY_LIMIT)
        argv = []
        named = (f"the default --threshold {DENSITY_LIMIT:g} (the {THRESHOLD_QUANTILE:g} quantile of the density at "
                 "the test views' depths)")
    with pytest.raises(SystemExit) as refused:
        main([str(run_dir), "--resolution", "4", *argv])
    line = refused.value.code
    match = re.fullmatch(rf"nerfexp-export: error: no surface at {re.escape(named)}: the field's densities on the "
                         r"5 x 5 x 5 grid over the box \[\[.*\]\] lie in \[(\S+), (\S+)\]; choose a threshold "
                         "between them", line)
    assert match and float(match[1]) < float(match[2]), line
    assert digests(run_dir) == before and not list(run_dir.glob(".export*"))


@pytest.mark.slow
def test_the_default_threshold_is_read_from_the_field_and_finds_its_surface(tiny_run, tmp_path, capsys):
    run_dir = shutil.copytree(tiny_run, tmp_path / "run")
    main([str(run_dir), "--resolution", "16"])  # no --threshold: the tiny run is far below the literature's 50
    summary = capsys.readouterr().out
    match = re.search(rf"triangles \(density (\S+), the {THRESHOLD_QUANTILE:g} quantile of the density at the "
                      r"test views' depths; \d+ x \d+ x \d+ grid\)", summary)
    assert match, summary
    threshold = float(match[1])
    comments, mesh = read_ply((run_dir / "export" / "mesh.ply").read_bytes())
    assert len(mesh["face"]) > 0 and f"density {match[1]} (the {THRESHOLD_QUANTILE:g} quantile" in comments[1]
    # the threshold is that quantile of the field's density at the exported points (the test views' depths)
    _, cloud = read_ply((run_dir / "export" / "points.ply").read_bytes())
    points = torch.from_numpy(np.stack([cloud["vertex"][n] for n in ("x", "y", "z")], 1))
    (_, _, _, module, _), _ = trained_run(run_dir, [], None)
    with torch.no_grad():
        sigma = final_field(module.renderer).density(points).double()
    at_or_above = (sigma >= float(f"{threshold:.6g}") * (1 - 1e-5)).double().mean().item()  # to the printed digits
    assert len(points) > 100 and 1 - THRESHOLD_QUANTILE <= at_or_above <= 1 - THRESHOLD_QUANTILE + 0.02, at_or_above


def test_a_default_threshold_needs_a_rendered_surface():
    with pytest.raises(NerfexpError, match="no pixel of the test views reaches --min-opacity"):
        field_threshold(BuiltInSceneField(), torch.zeros(0, 3), batch=10, device="cpu")
    # the built-in field at points on its objects' surfaces: density THRESHOLD at every one
    surface = torch.from_numpy(true_surface(0.05))[:400]
    assert field_threshold(BuiltInSceneField(), surface, batch=64, device="cpu") == pytest.approx(THRESHOLD)
