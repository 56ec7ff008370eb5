"""``nerfexp-export RUN_DIR``: a trained run's scene as a coloured mesh and a coloured point cloud, PLY files
that MeshLab, Blender, Open3D and CloudCompare open.

What an export leaves in ``RUN_DIR/export/`` (the folder is replaced as a whole once both files are
written, so a reader sees the previous export or the new one, never a part; an ``export/`` holding a file
that the run directory's manifest does not show to be nerfexp-export's, ``nerfexp.manifest``, is refused
with one line before any work, and checked again before it is replaced):

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
from pathlib import Path

import torch
from omegaconf import DictConfig

from nerfexp.commands.arguments import (
    add_chunk_argument,
    add_run_arguments,
    command_parser,
    fitting,
    positive,
    say_unfinished,
)
from nerfexp.commands.console import run_command
from nerfexp.data.base import Scene
from nerfexp.errors import NerfexpError
from nerfexp.files import atomic_directory
from nerfexp.geometry.surfaces import grid_shape
from nerfexp.manifest import check_ours, folder_files, record_folder
from nerfexp.pixels import to_uint8
from nerfexp.products.mesh import (
    THRESHOLD_QUANTILE,
    box_text,
    export_box,
    extract_mesh,
    field_threshold,
    final_field,
    view_points,
)
from nerfexp.products.ply import face_rows, ply_bytes, vertex_rows
from nerfexp.products.trained import TrainedRun, load_run, run_scene
from nerfexp.rundir.layout import EXPORT_DIR
from nerfexp.sizes import grid_bytes

MESH = "mesh.ply"
DENSITY_LIMIT = float(torch.finfo(torch.float32).max)  # the field's densities are float32 numbers
POINTS = "points.ply"


def refuse_ndc(run_dir: Path, saved: DictConfig) -> None:
    """A NerfexpError for a run trained on NDC rays (its saved config's ``data.ndc``: an override cannot
    change the space its field was trained in)."""
    if saved.data.get("ndc", False):
        raise NerfexpError(f"{run_dir} was trained on NDC rays (data.ndc=true, a forward-facing scene): its "
                           "field lives in NDC space, where a mesh and points would be distorted; nerfexp-export "
                           "exports runs trained on world rays")


def trained_run(run: Path, overrides: list[str], chunk: int | None) -> tuple[TrainedRun, Scene]:
    """The run at ``run`` read back (``load_run``), runs trained on NDC rays refused before their checkpoint is
    read (``refuse_ndc``), and its scene."""
    loaded = load_run(run, overrides, chunk, refuse=refuse_ndc)
    return loaded, run_scene(loaded.run_dir, loaded.cfg)


def export_run(run: Path, overrides: list[str], resolution: int, threshold: float | None, chunk: int | None,
               min_opacity: float) -> str:
    """Export the run at ``run`` (``trained_run``) into ``RUN_DIR/export``: ``points.ply`` (``view_points``
    of its test views) and ``mesh.ply`` (``extract_mesh`` at ``threshold``; None: ``field_threshold`` at the
    points). Returns a one-line summary."""
    (run_dir, checkpoint, _, module, step), scene = trained_run(run, overrides, chunk)
    say_unfinished("nerfexp-export", run_dir, checkpoint, step)
    out_dir = run_dir / EXPORT_DIR
    check_export_folder(run_dir)
    renderer = module.renderer
    box = export_box(renderer, scene)
    views = scene.views("test")
    points, point_colours = view_points(module, scene, views, min_opacity)
    # the field is evaluated as many points at a time as a chunk of rays evaluates: the memory of rendering
    batch = module.chunk * renderer.samples_per_ray
    default = None  # how the threshold was read, where none is given
    if threshold is None:
        threshold = field_threshold(final_field(renderer), points, batch, module.device)
        default = f"the {THRESHOLD_QUANTILE:g} quantile of the density at the test views' depths"
    mesh, mesh_colours = extract_mesh(final_field(renderer), box, resolution, threshold, batch, module.device,
                                      default=default)
    source = default or "given"

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
        check_export_folder(run_dir)  # again: the export took a while
    record_folder(run_dir, EXPORT_DIR)
    return (f"{MESH}: {len(mesh.vertices)} vertices, {len(mesh.faces)} triangles (density {threshold:g}, "
            f"{source}; {shape} grid); {POINTS}: {len(points)} points from {len(views)} test views; "
            f"written to {out_dir}")


def check_export_folder(run_dir: Path) -> None:
    """A NerfexpError where ``RUN_DIR/export``, which an export replaces as a whole, holds a file that the run
    directory's manifest does not show to be an export's (``nerfexp.manifest.check_ours``)."""
    check_ours(run_dir, folder_files(run_dir, EXPORT_DIR), "nerfexp-export",
               "move {it} elsewhere: nerfexp-export replaces this folder as a whole")


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
    parser.add_argument("--threshold", type=positive(float, DENSITY_LIMIT),
                        help="mesh: the density at its surface (default: read from the field, the "
                             f"{THRESHOLD_QUANTILE:g} quantile of its density where the test views' rays that "
                             "reach --min-opacity end, at their rendered depths; the summary prints the value "
                             "used). Density sigma absorbs 1 - exp(-sigma h) of the light crossing a width h: 50, "
                             "the original NeRF code's value for converged fields, absorbs 63%% over 0.02 scene "
                             "units, 99%% over 0.09 (docs/export.md)")
    parser.add_argument("--min-opacity", type=_opacity, default=0.5,
                        help="points: the test views' pixels whose rendered opacity is at least this, in (0, 1], "
                             "become points (default 0.5)")
    add_chunk_argument(parser, "; the mesh's grid is evaluated as many points at a time as CHUNK rays evaluate")
    return parser


def main(argv: list[str] | None = None) -> None:
    """The ``nerfexp-export`` command (``build_parser``)."""
    run_command(build_parser(), argv, lambda args: export_run(args.run, args.overrides, args.resolution,
                                                              args.threshold, args.chunk, args.min_opacity))


if __name__ == "__main__":
    main()
