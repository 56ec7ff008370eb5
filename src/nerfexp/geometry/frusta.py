"""Cameras' views as pyramids: the four planes through a camera's centre that bound every pixel ray of its
image (``view_planes``), which points a view holds (``in_view``), and the nearest and farthest points of a
box that a view holds (``box_reach``), the ray bounds a scene box gives.

Conventions: a view's planes are inward unit normals n [N, 4, 3] in world coordinates through the camera's
centre o, and a point p lies in the view where n . (p - o) >= 0 for all four. A view that reaches 90 degrees
or more from its axis (a wide fisheye) is no pyramid: its normals are zero, and it holds every point.
"""

import itertools

import torch
from torch import Tensor

from nerfexp.geometry.lenses import Intrinsics, pixel_rays

FEASIBLE = 1e-9  # a candidate point lies in the box and the view within this fraction of the scene's size
INDEPENDENT = 1e-9  # unit normals whose Gram determinant is below this are taken as dependent


def border_centres(height: int, width: int) -> Tensor:
    """Image coordinates [K, 2] float64 (u, v) of every pixel centre on an image's border, corners included."""
    u = torch.arange(width, dtype=torch.float64) + 0.5
    v = torch.arange(height, dtype=torch.float64) + 0.5
    top, bottom = torch.stack([u, torch.full_like(u, 0.5)], -1), torch.stack([u, torch.full_like(u, height - 0.5)], -1)
    left, right = torch.stack([torch.full_like(v, 0.5), v], -1), torch.stack([torch.full_like(v, width - 0.5), v], -1)
    return torch.cat([top, bottom, left, right])


def view_planes(c2w: Tensor, intrinsics: Intrinsics, height: int, width: int) -> Tensor:
    """The inward unit normals [N, 4, 3] (world) of the pyramid of each camera ``c2w`` [N, 4, 4] with lens
    ``intrinsics`` [N] and images of ``height`` x ``width`` pixels: the smallest pyramid about the camera's
    axis with a rectangular section that holds every pixel centre's ray.

    A ray d (camera coordinates, looking down -z) has slopes (u, w) = (d_x, d_y) / -d_z; the pyramid is
    u0 <= u <= u1, w0 <= w <= w1 over the pixel rays, i.e. n . d >= 0 with n = (1, 0, u0), (-1, 0, -u1),
    (0, 1, w0), (0, -1, -w1), normalized. An ideal pinhole maps pixels to slopes affinely, so the corner pixel
    centres' rays span exactly the pixel rays' pyramid; a distorted lens's slopes are bounded over every border
    pixel centre (the region inside the border holds the interior's rays, and a region's bounds are its
    border's). A view whose rays reach 90 degrees from the axis or beyond gets zero normals (no pyramid).
    Example: a centred pinhole of focal f and width W has u1 = (W / 2 - 1 / 2) / f."""
    c2w = c2w.to(torch.float64)
    lens = intrinsics.to(torch.float64)
    distorted = bool(lens.is_distorted().any())
    pixels = border_centres(height, width) if distorted else torch.tensor(
        [[0.5, 0.5], [width - 0.5, 0.5], [0.5, height - 0.5], [width - 0.5, height - 0.5]], dtype=torch.float64)
    d = pixel_rays(pixels, lens.unsqueeze(1))  # [N, K, 3], camera coordinates
    forward = -d[..., 2]
    pyramid = (forward > 0).all(-1)  # [N]
    safe = torch.where(forward > 0, forward, 1.0)
    u, w = d[..., 0] / safe, d[..., 1] / safe  # [N, K] slopes
    zero, one = torch.zeros_like(u[:, 0]), torch.ones_like(u[:, 0])
    normals = torch.stack([torch.stack([one, zero, u.amin(-1)], -1), torch.stack([-one, zero, -u.amax(-1)], -1),
                           torch.stack([zero, one, w.amin(-1)], -1), torch.stack([zero, -one, -w.amax(-1)], -1)], 1)
    normals = normals / torch.linalg.vector_norm(normals, dim=-1, keepdim=True)  # [N, 4, 3]
    world = torch.einsum("nij,nkj->nki", c2w[:, :3, :3], normals)
    return torch.where(pyramid[:, None, None], world, torch.zeros_like(world))


def in_view(points: Tensor, c2w: Tensor, normals: Tensor) -> Tensor:
    """[N, P] bool: whether each point ``points`` [P, 3] lies in each camera's view (``c2w`` [N, 4, 4], its
    pyramid's ``normals`` [N, 4, 3] from ``view_planes``): n . (p - o) >= 0 for all four planes, within
    rounding (``FEASIBLE`` x |p - o|: a point on a border pixel's ray lies on a plane)."""
    offsets = points[None].to(torch.float64) - c2w[:, None, :3, 3].to(torch.float64)  # [N, P, 3]
    slack = -FEASIBLE * torch.linalg.vector_norm(offsets, dim=-1, keepdim=True)
    return (torch.einsum("nkj,npj->npk", normals.to(torch.float64), offsets) >= slack).all(-1)


def box_reach(c2w: Tensor, normals: Tensor, box: Tensor) -> tuple[Tensor, Tensor]:
    """(nearest [N], farthest [N]): the distances from each camera's centre (``c2w`` [N, 4, 4]) to the nearest
    and the farthest point of ``box`` [2, 3] that its view (``normals`` [N, 4, 3], ``view_planes``) holds; inf
    and -inf where the view holds none of the box. Every ray of a view enters the box no nearer than the
    nearest (0 where the camera is inside) and leaves it no farther than the farthest, and some ray of the
    view does each (the bound is exact, not sampled).

    The set K = box & view is a convex polyhedron {p : A p >= b} of ten planes (the box's six, the view's
    four). Its nearest point to o is the projection of o onto the planes active there (KKT), and its farthest
    (|p - o| is convex) is a vertex, where three planes meet. So every set S of at most three planes with
    independent normals gives a candidate, the projection p = o + A_S^T (A_S A_S^T)^-1 (b_S - A_S o) of o
    onto their intersection, and the nearest and farthest candidates that lie in K are the answer (o itself,
    S empty, lies in K where the camera is inside the box). Float64 throughout."""
    c2w, normals, box = c2w.to(torch.float64), normals.to(torch.float64), box.to(torch.float64)
    n = len(c2w)
    origins = c2w[:, :3, 3]  # [N, 3]
    eye = torch.eye(3, dtype=torch.float64)
    box_normals = torch.cat([eye, -eye])  # p >= lower, -p >= -upper
    box_offsets = torch.cat([box[0], -box[1]])
    A = torch.cat([box_normals.expand(n, 6, 3), normals], 1)  # [N, 10, 3]
    b = torch.cat([box_offsets.expand(n, 6), (normals * origins[:, None]).sum(-1)], 1)  # [N, 10]
    size = float((box[1] - box[0]).norm() + box.abs().max() + origins.abs().max())
    candidates = [origins[:, None]]  # [N, C, 3] per subset size; S empty: o
    for k in (1, 2, 3):
        subsets = torch.tensor(list(itertools.combinations(range(A.shape[1]), k)))  # [C, k]
        A_S, b_S = A[:, subsets], b[:, subsets]  # [N, C, k, 3], [N, C, k]
        gram = A_S @ A_S.transpose(-1, -2)  # [N, C, k, k]
        independent = torch.linalg.det(gram) > INDEPENDENT
        gram = torch.where(independent[..., None, None], gram, torch.eye(k, dtype=torch.float64))
        residual = b_S - (A_S @ origins[:, None, :, None]).squeeze(-1)  # [N, C, k]
        step = (A_S.transpose(-1, -2) @ torch.linalg.solve(gram, residual)[..., None]).squeeze(-1)
        candidates.append(torch.where(independent[..., None], origins[:, None] + step, torch.nan))
    points = torch.cat(candidates, 1)  # [N, C, 3]
    inside = ((points @ A.transpose(1, 2)) - b[:, None] >= -FEASIBLE * size).all(-1)  # NaN fails
    distances = torch.linalg.vector_norm(points - origins[:, None], dim=-1)
    nearest = torch.where(inside, distances, torch.inf).amin(-1)
    farthest = torch.where(inside, distances, -torch.inf).amax(-1)
    return nearest, farthest
