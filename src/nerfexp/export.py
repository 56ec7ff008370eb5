"""``nerfexp-export RUN_DIR``: a trained run's scene as a coloured mesh and a coloured point cloud, PLY files
that MeshLab, Blender, Open3D and CloudCompare open.

What an export leaves in ``RUN_DIR/export/`` (the folder is replaced as a whole once both files are
written, so a reader sees the previous export or the new one, never a part; an ``export/`` holding anything
else is refused with one line before any work):

- ``mesh.ply``: the surface where the field's density crosses ``--threshold``, by marching cubes on a grid
  over the box (``--resolution`` cells along its longest edge): vertices with outward normals and colours,
  and triangles.
- ``points.ply``: one point per pixel of each test view whose rendered opacity reaches ``--min-opacity``,
  where its ray ends (origin + depth x direction), with the colour of the light it absorbed.

The field is the one final renders use: the fine network where the run is hierarchical. The box is the one
the renderer's bounded modules work in (hash grid encoding, occupancy grid: saved in the checkpoint), else
the scene's own (``Scene.box``). The occupancy grid is not applied to the densities: it marks empty only
cells far fainter than any surface. A vertex's colour is the field's colour at the vertex seen along its
inward normal (view direction = -normal), as a camera facing the surface there sees it: the colour is
view-dependent, and that is the one view every point of a surface has. Runs trained on NDC rays
(forward-facing LLFF scenes, ``data.ndc=true``) are refused: their field lives in NDC space, where a mesh
and points would be distorted.
"""

import argparse
import math
from pathlib import Path

import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig
from torch import Tensor, nn
from tqdm import tqdm

from nerfexp.arguments import add_run_arguments, command_parser, fitting, positive
from nerfexp.console import run_command
from nerfexp.data.base import Scene
from nerfexp.data.rays import WholeImages, model_batch
from nerfexp.data.views import Views
from nerfexp.errors import NerfexpError
from nerfexp.files import TEMPORARY, atomic_directory, foreign_entries, foreign_message
from nerfexp.geometry.surfaces import Mesh, grid_points, grid_shape, isosurface, ray_points
from nerfexp.memory import grid_bytes
from nerfexp.nerf.bounds import Bounded
from nerfexp.nerf.volume_renderer import VolumeRenderer
from nerfexp.pixels import to_uint8
from nerfexp.ply import face_rows, ply_bytes, vertex_rows
from nerfexp.rundir import EXPORT_DIR, TrainedRun, load_run
from nerfexp.training.module import NeRFModule

MESH = "mesh.ply"
POINTS = "points.ply"
MADE = (MESH, POINTS, *TEMPORARY)  # what an export leaves in its folder
THRESHOLD_QUANTILE = 0.25  # the default threshold: this quantile of the density at the test views' depths


def final_field(renderer: VolumeRenderer) -> nn.Module:
    """The network that final renders use: the fine one, or the only one without hierarchy."""
    return renderer.fine if renderer.fine is not None else renderer.coarse


def export_box(renderer: VolumeRenderer, scene: Scene) -> Tensor:
    """The box [2, 3] (float64, on the host) to mesh: the one the renderer's bounded modules (hash grid
    encoding, occupancy grid) work in, where they have one; else the scene's (``Scene.box``; the training
    views are loaded only where the scene has no box of its own)."""
    bounded = [m for m in renderer.modules() if isinstance(m, Bounded) and m.has_bounds]
    if bounded:
        return bounded[0].aabb.detach().double().cpu()
    views = scene.views("train") if scene.aabb is None and scene.bounding_box() is None else None
    return scene.box(views, renderer.near, renderer.far).double()


def box_text(aabb: Tensor) -> str:
    """``[[x0, y0, z0], [x1, y1, z1]]`` rounded to 4 significant digits, for messages and file headers."""
    return str([[float(f"{v:.4g}") for v in row] for row in aabb.tolist()])


@torch.no_grad()
def grid_densities(field: nn.Module, aabb: Tensor, shape: tuple[int, int, int], batch: int,
                   device: str | torch.device) -> np.ndarray:
    """The field's density (``field.density``: positions [N, 3] -> sigma [N]) at every point of the grid
    ``shape`` over ``aabb`` (``nerfexp.geometry.surfaces``), ``batch`` points at a time on ``device``, with a
    progress bar: [X, Y, Z] float32."""
    n = math.prod(shape)
    values = torch.empty(n, dtype=torch.float32)
    with tqdm(total=n, desc="densities", unit="point", unit_scale=True, disable=None) as bar:
        for start in range(0, n, batch):
            indices = torch.arange(start, min(start + batch, n))
            points = grid_points(aabb, shape, indices).to(device, torch.float32)
            values[start:start + len(indices)] = field.density(points).float().cpu()
            bar.update(len(indices))
    return values.reshape(shape).numpy()


@torch.no_grad()
def vertex_colours(field: nn.Module, mesh: Mesh, batch: int, device: str | torch.device) -> np.ndarray:
    """8-bit colours [V, 3] of the mesh's vertices: the field's colour at each vertex seen along its inward
    normal (view direction -normal, what a camera facing the surface there sees), ``batch`` at a time."""
    positions = torch.from_numpy(mesh.vertices).float().split(batch)
    directions = torch.from_numpy(-mesh.normals).float().split(batch)
    colours = [torch.zeros(0, 3)]
    for x, d in tqdm(zip(positions, directions), total=len(positions), desc="vertex colours", disable=None):
        rgb, _ = field(x.to(device), d.to(device))
        colours.append(rgb.float().cpu())
    return to_uint8(torch.cat(colours))


def extract_mesh(field: nn.Module, aabb: Tensor, resolution: int, threshold: float, batch: int,
                 device: str | torch.device) -> tuple[Mesh, np.ndarray]:
    """The surface where ``field``'s density crosses ``threshold`` inside ``aabb`` [2, 3], on a grid of
    ``resolution`` cells along the box's longest edge (``grid_shape``), and its vertices' colours
    (``vertex_colours``): ``(mesh, colours [V, 3] uint8)``. A NerfexpError where no density in the box
    lies above ``threshold``, or none at or below it."""
    shape = grid_shape(aabb, resolution)
    densities = grid_densities(field, aabb, shape, batch, device)
    low, high = float(densities.min()), float(densities.max())
    if not low <= threshold < high:
        raise NerfexpError(f"no surface at --threshold {threshold:g}: the field's densities on the "
                           f"{' x '.join(map(str, shape))} grid over the box {box_text(aabb)} lie in "
                           f"[{low:.4g}, {high:.4g}]; choose a threshold between them")
    mesh = isosurface(densities, threshold, aabb)
    return mesh, vertex_colours(field, mesh, batch, device)


@torch.no_grad()
def field_threshold(field: nn.Module, points: Tensor, batch: int, device: str | torch.device) -> float:
    """``--threshold``'s default, read from the field itself: the ``THRESHOLD_QUANTILE`` quantile of its
    density (``field.density``: positions [N, 3] -> sigma [N]) at ``points`` [P, 3], where the test views'
    rays that the field made opaque end (``view_points``), ``batch`` at a time. The density at which a
    field draws its surfaces depends on how far it has trained (a field trained briefly is nowhere as
    dense as a converged one), so no fixed number suits every run, while the rendered depths lie on the
    surfaces the run renders: most of them end up inside the mesh, the haze of a few rays aside. A
    NerfexpError where ``points`` is empty."""
    if len(points) == 0:
        raise NerfexpError("no default --threshold: no pixel of the test views reaches --min-opacity, so the "
                           "field has no rendered surface to read a density from; give --threshold")
    sigma = torch.cat([field.density(x.to(device, torch.float32)).double().cpu() for x in points.split(batch)])
    return float(sigma.sort().values[round(THRESHOLD_QUANTILE * (len(sigma) - 1))])  # nearest rank


def absorbed_colour(rgb: Tensor, opacity: Tensor, background: Tensor) -> Tensor:
    """The colour [..., 3] of the light that rays absorbed: the rendered ``rgb`` [..., 3] = opacity c +
    (1 - opacity) ``background`` [3] solved for c, clamped to [0, 1]. ``opacity`` [...] must be positive
    (``view_points`` keeps rays whose opacity reaches its ``min_opacity`` > 0)."""
    return ((rgb - (1 - opacity[..., None]) * background) / opacity[..., None]).clamp(0, 1)


@torch.no_grad()
def view_points(module: NeRFModule, scene: Scene, views: Views, min_opacity: float) -> tuple[Tensor, Tensor]:
    """A point per pixel of ``views`` whose rendered opacity is at least ``min_opacity`` (in (0, 1]), where
    its ray ends, and its colour: ``(points [P, 3], colours [P, 3] in [0, 1])``, on the host.

    Each view is rendered as ``nerfexp-eval`` renders it (``WholeImages``, ``model_batch``,
    ``NeRFModule.render_image``, ``module.chunk`` rays at a time); a point is origin + depth x direction
    (``ray_points``: the depth is the expected distance at which the absorbed light stopped), its colour
    that of the absorbed light (``absorbed_colour``: the rendered colour without the background)."""
    background = module.renderer.background
    images = WholeImages(views, background.cpu())
    points, colours = [torch.zeros(0, 3)], [torch.zeros(0, 3)]
    for index in tqdm(range(len(images)), desc="test views", unit="view", disable=None):
        batch = model_batch(scene, images[index])
        origins, directions, viewdirs = (batch[key].to(module.device) for key in ("origins", "directions", "viewdirs"))
        image = module.render_image(origins, directions, viewdirs)
        keep = image["opacity"] >= min_opacity  # [H, W]
        points.append(ray_points(origins[keep], directions[keep], image["depth"][keep]).float().cpu())
        colours.append(absorbed_colour(image["rgb"][keep], image["opacity"][keep], background).float().cpu())
    return torch.cat(points), torch.cat(colours)


def refuse_ndc(run_dir: Path, saved: DictConfig) -> None:
    """A NerfexpError for a run trained on NDC rays (its saved config's ``data.ndc``: an override cannot
    change the space its field was trained in)."""
    if saved.data.get("ndc", False):
        raise NerfexpError(f"{run_dir} was trained on NDC rays (data.ndc=true, a forward-facing scene): its "
                           "field lives in NDC space, where a mesh and points would be distorted; nerfexp-export "
                           "exports runs trained on world rays")


def trained_run(run: Path, overrides: list[str], chunk: int | None) -> tuple[TrainedRun, Scene]:
    """The run at ``run`` read as ``nerfexp-eval`` reads it (``load_run``), runs trained on NDC rays refused
    before their checkpoint is read (``refuse_ndc``), and its scene."""
    loaded = load_run(run, overrides, chunk, refuse=refuse_ndc)
    return loaded, instantiate(loaded.cfg.data)


def export_run(run: Path, overrides: list[str], resolution: int, threshold: float | None, chunk: int | None,
               min_opacity: float) -> str:
    """Export the run at ``run`` (``trained_run``) into ``RUN_DIR/export``: ``points.ply`` (``view_points``
    of its test views) and ``mesh.ply`` (``extract_mesh`` at ``threshold``; None: ``field_threshold`` at the
    points). Returns a one-line summary."""
    (run_dir, checkpoint, _, module, step), scene = trained_run(run, overrides, chunk)
    out_dir = run_dir / EXPORT_DIR
    if foreign := foreign_entries(out_dir, MADE):  # the folder is replaced as a whole: it must be an export
        raise NerfexpError(foreign_message(out_dir, foreign, "nerfexp-export", "move them elsewhere: "
                                           "nerfexp-export replaces this folder as a whole"))
    renderer = module.renderer
    box = export_box(renderer, scene)
    views = scene.views("test")
    points, point_colours = view_points(module, scene, views, min_opacity)
    # the field is evaluated as many points at a time as a chunk of rays evaluates: the memory of rendering
    batch = module.chunk * renderer.samples_per_ray
    source = "given"
    if threshold is None:
        threshold = field_threshold(final_field(renderer), points, batch, module.device)
        source = f"the {THRESHOLD_QUANTILE:g} quantile of the density at the test views' depths"
    mesh, mesh_colours = extract_mesh(final_field(renderer), box, resolution, threshold, batch, module.device)

    shape = " x ".join(map(str, grid_shape(box, resolution)))
    made = f"nerfexp-export of {checkpoint} (step {step})"
    with atomic_directory(out_dir, replace=True) as new:
        mesh_elements = {"vertex": vertex_rows(mesh.vertices, mesh_colours, mesh.normals),
                         "face": face_rows(mesh.faces)}
        (new / MESH).write_bytes(ply_bytes(mesh_elements, [
            made, f"density {threshold:g} ({source}) crossed on a {shape} grid over the box {box_text(box)}",
            "vertex colours: the field seen along the inward normal"]))
        (new / POINTS).write_bytes(ply_bytes({"vertex": vertex_rows(points.numpy(), to_uint8(point_colours))}, [
            made, f"pixels of {len(views)} test views with opacity >= {min_opacity:g}, at their depth along the ray",
            "colours: the rendered colour without the background"]))
    return (f"{MESH}: {len(mesh.vertices)} vertices, {len(mesh.faces)} triangles (density {threshold:g}, "
            f"{source}; {shape} grid); {POINTS}: {len(points)} points from {len(views)} test views; "
            f"written to {out_dir}")


def _opacity(text: str) -> float:
    value = float(text)
    if not 0 < value <= 1:
        raise argparse.ArgumentTypeError(f"expected an opacity in (0, 1], got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    """``nerfexp-export RUN_DIR`` (or a checkpoint file in it): the trained scene as a coloured mesh
    (marching cubes on the field's density) and a coloured point cloud (the test views' rendered depths),
    RUN_DIR/export/mesh.ply and points.ply."""
    parser = command_parser("nerfexp-export", build_parser.__doc__)
    add_run_arguments(parser)
    parser.add_argument("--resolution", type=fitting(positive(int), grid_bytes, "a grid of N^3 densities"),
                        default=128,
                        help="mesh: grid cells along the box's longest edge, the other edges getting cells of "
                             "the same size (default 128: about 2 million density evaluations for a cube)")
    parser.add_argument("--threshold", type=positive(float),
                        help="mesh: the density at its surface (default: read from the field, the "
                             f"{THRESHOLD_QUANTILE:g} quantile of its density where the test views' rays that "
                             "reach --min-opacity end, at their rendered depths; the summary prints the value "
                             "used). Density sigma absorbs 1 - exp(-sigma h) of the light crossing a width h: 50, "
                             "the original NeRF code's value for converged fields, absorbs 63%% over 0.02 scene "
                             "units, 99%% over 0.09 (docs/export.md)")
    parser.add_argument("--min-opacity", type=_opacity, default=0.5,
                        help="points: the test views' pixels whose rendered opacity is at least this, in (0, 1], "
                             "become points (default 0.5)")
    parser.add_argument("--chunk", type=positive(int),
                        help="rays rendered at once for the points (default: the run's model.chunk); the mesh's "
                             "grid is evaluated as many points at a time as CHUNK rays evaluate")
    return parser


def main(argv: list[str] | None = None) -> None:
    """The ``nerfexp-export`` command (``build_parser``)."""
    run_command(build_parser(), argv, lambda args: export_run(args.run, args.overrides, args.resolution,
                                                              args.threshold, args.chunk, args.min_opacity))


if __name__ == "__main__":
    main()
