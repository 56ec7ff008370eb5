"""The occupancy grid's fused lookup (src/nerfexp/kernels/occupancy_lookup.cpp) against independent truth, the
cells of known points in a known pattern, and bit for bit against the torch path it replaces (``cell_indices``,
NERFEXP_KERNELS=off): points on the box's faces and its cells' faces, just inside and outside, NaN and infinite,
boxes of unequal sides, batches of any shape and none; the fallback where it does not run, and its one-line
errors."""

import pytest
import torch

from nerfexp import kernels
from nerfexp.nerf.occupancy import LOOKUP_KERNEL, OccupancyGrid

FUSED = kernels.kernel(LOOKUP_KERNEL)
needs_kernel = pytest.mark.skipif(FUSED is None, reason="the occupancy lookup's kernel was not built (no C++ compiler)")

BOX = [[-1.0, -0.5, 0.0], [1.0, 1.5, 3.0]]  # sides 2, 2 and 3: the axes scale differently


def patterned_grid(resolution: int) -> OccupancyGrid:
    """A grid over ``BOX`` whose cell (i, j, k) is occupied where (5 i + 3 j + k) mod 7 < 3 (``pattern``): a swapped
    axis or a cell off by one gives another answer somewhere."""
    grid = OccupancyGrid(resolution=resolution, aabb=BOX)
    ijk = torch.cartesian_prod(*[torch.arange(resolution)] * 3)  # flat order (i R + j) R + k
    grid.occupied.copy_(pattern(ijk))
    return grid


def pattern(ijk: torch.Tensor) -> torch.Tensor:
    """Cells (i, j, k) [M, 3] -> occupied [M]: (5 i + 3 j + k) mod 7 < 3."""
    return (5 * ijk[:, 0] + 3 * ijk[:, 1] + ijk[:, 2]) % 7 < 3


def awkward_points(resolution: int) -> torch.Tensor:
    """Points [M, 3] (float32): random in a box larger than ``BOX``, on cell faces (u R an integer) including the
    box's lower faces (inside) and upper faces (outside), one float below and above them, NaN and infinities."""
    generator = torch.Generator().manual_seed(5)
    lo, hi = torch.tensor(BOX)
    unit = [torch.rand(400, 3, generator=generator) * 1.4 - 0.2,
            torch.randint(0, resolution + 1, (200, 3), generator=generator) / resolution]
    points = lo + torch.cat(unit) * (hi - lo)
    faces = torch.cat([lo[None], hi[None]]).repeat(20, 1)  # every corner's coordinates, nudged both ways
    nudged = [torch.nextafter(faces, faces + 1), torch.nextafter(faces, faces - 1)]
    special = torch.tensor([[float("nan"), 0.0, 1.0], [0.0, float("inf"), 1.0], [0.0, 0.5, -float("inf")],
                            [float("nan")] * 3])
    return torch.cat([points, faces, *nudged, special])


@needs_kernel
@pytest.mark.parametrize("resolution", [1, 4, 7, 64])
def test_the_kernel_finds_each_cell_centres_occupancy_and_matches_the_torch_path_bit_for_bit(resolution, monkeypatch):
    grid = patterned_grid(resolution)
    lo, hi = torch.tensor(BOX)
    ijk = torch.cartesian_prod(*[torch.arange(resolution)] * 3)
    centres = lo + (ijk + 0.5) / resolution * (hi - lo)  # cell (i, j, k)'s centre: independent truth
    assert grid.lookup_kernel(centres) is FUSED
    assert torch.equal(grid.occupied_at(centres), pattern(ijk))
    points = awkward_points(resolution)
    fused = grid.occupied_at(points)
    monkeypatch.setenv(kernels.SWITCH, "off")
    assert grid.lookup_kernel(points) is None
    assert torch.equal(fused, grid.occupied_at(points))
    assert not fused[-4:].any()  # NaN and infinite points lie in no cell


@needs_kernel
def test_the_kernel_keeps_the_batch_shape_takes_strided_points_and_gives_no_gradient():
    grid = patterned_grid(8)
    points = awkward_points(8)[:360].reshape(6, 20, 3, 3)[..., 0, :]  # [6, 20, 3], not contiguous
    points.requires_grad_(True)
    assert not points.is_contiguous()
    fused = grid.occupied_at(points)
    assert fused.shape == (6, 20) and fused.dtype == torch.bool and not fused.requires_grad
    expected = grid.occupied_at(points.detach().double())  # float64 points: the torch path, the reference
    assert grid.lookup_kernel(points.double()) is None and torch.equal(fused, expected)
    assert grid.occupied_at(torch.empty(0, 5, 3)).shape == (0, 5)


@needs_kernel
@pytest.mark.parametrize(("args", "message"), [
    ((torch.zeros(4, 2), torch.zeros(2, 3), torch.ones(8, dtype=torch.bool), 2), "points must be [N, 3]"),
    ((torch.zeros(4, 3), torch.zeros(3, 3), torch.ones(8, dtype=torch.bool), 2), "box must be [2, 3]"),
    ((torch.zeros(4, 3), torch.zeros(2, 3), torch.ones(9, dtype=torch.bool), 2), "occupied must be [8]"),
    ((torch.zeros(4, 3), torch.zeros(2, 3), torch.ones(8), 2), "occupied must be bool"),
    ((torch.zeros(4, 3).double(), torch.zeros(2, 3), torch.ones(8, dtype=torch.bool), 2), "must be float32"),
    ((torch.zeros(4, 3), torch.zeros(2, 3), torch.ones(1, dtype=torch.bool), 0), "0 cells per side"),
    ((torch.zeros(3, 4).t(), torch.zeros(2, 3), torch.ones(8, dtype=torch.bool), 2), "points is not contiguous"),
])
def test_the_kernel_refuses_inputs_it_cannot_read_in_one_line(args, message):
    with pytest.raises(RuntimeError, match=f"occupancy_lookup: .*{message.replace('[', '.').replace(']', '.')}"):
        FUSED.occupied_at(*args)
