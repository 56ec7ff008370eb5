"""A trained field as geometry: its density on a grid over a box, the surface where it crosses a
threshold (marching cubes) with colours and outward normals, the threshold read from the field, and
the points where the test views' rays end with the colour of the light they absorbed."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor, nn
from tqdm import tqdm

from nerfexp.data.base import Scene
from nerfexp.data.rays import WholeImages, model_batch
from nerfexp.data.views import Views
from nerfexp.errors import NerfexpError
from nerfexp.geometry.surfaces import Mesh, grid_points, grid_shape, isosurface, ray_points
from nerfexp.nerf.bounds import Bounded
from nerfexp.nerf.volume_renderer import VolumeRenderer
from nerfexp.pixels import to_uint8

if TYPE_CHECKING:  # annotations only: it imports Lightning, which a command stopping at bad input need not wait for
    from nerfexp.training.module import NeRFModule

THRESHOLD_QUANTILE = 0.25  # the default threshold: this quantile of the density at the test views' depths


class WorldField(nn.Module):
    """A field of a renderer with a contraction queried at world positions: ``density(x)`` and ``forward(x, d)``
    of the field at the contracted x (``VolumeRenderer.field_positions``)."""

    def __init__(self, field: nn.Module, renderer: VolumeRenderer):
        super().__init__()
        self.field, self.positions = field, renderer.field_positions

    def density(self, positions: Tensor) -> Tensor:
        return self.field.density(self.positions(positions))

    def forward(self, positions: Tensor, directions: Tensor):
        return self.field(self.positions(positions), directions)


def final_field(renderer: VolumeRenderer) -> nn.Module:
    """The network that final renders use (the fine one, or the only one without hierarchy), taking world
    positions (``WorldField`` where the renderer contracts them)."""
    field = renderer.fine if renderer.fine is not None else renderer.coarse
    return field if renderer.contraction is None else WorldField(field, renderer)


def export_box(renderer: VolumeRenderer, scene: Scene) -> Tensor:
    """The box [2, 3] (float64, on the host) to mesh: with a contraction, the cube around its inner region (the
    unbounded world beyond it has no box); else the one the renderer's bounded modules (hash grid
    encoding, occupancy grid) work in, where they have one; else the scene's (``Scene.box``; the training
    views are loaded only where the scene has no box of its own)."""
    if renderer.contraction is not None:
        centre, radius = renderer.contraction.centre.double().cpu(), float(renderer.contraction.radius)
        return torch.stack([centre - radius, centre + radius])
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
        colours.append(field(x.to(device), d.to(device)).rgb.float().cpu())
    return to_uint8(torch.cat(colours))


def extract_mesh(field: nn.Module, aabb: Tensor, resolution: int, threshold: float, batch: int,
                 device: str | torch.device, default: str | None = None) -> tuple[Mesh, np.ndarray]:
    """The surface where ``field``'s density crosses ``threshold`` inside ``aabb`` [2, 3], on a grid of
    ``resolution`` cells along the box's longest edge (``grid_shape``), and its vertices' colours
    (``vertex_colours``): ``(mesh, colours [V, 3] uint8)``. A NerfexpError where no density in the box
    lies above ``threshold``, or none at or below it; ``default`` says how the threshold was read where the
    user gave none (``field_threshold``), so that the error names it as the default, not as their own."""
    shape = grid_shape(aabb, resolution)
    densities = grid_densities(field, aabb, shape, batch, device)
    low, high = float(densities.min()), float(densities.max())
    if not low <= threshold < high:
        named = f"--threshold {threshold:g}"
        if default is not None:
            named = f"the default {named} ({default})"
        raise NerfexpError(f"no surface at {named}: the field's densities on the "
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
