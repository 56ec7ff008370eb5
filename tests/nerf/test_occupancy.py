"""The occupancy grid (``nerfexp.nerf.occupancy``), and skipping and early termination in the renderer,
against analytic density fields whose densities are known everywhere."""

import math
from types import SimpleNamespace

import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate

from nerfexp.nerf.fields import FieldOutputs
from nerfexp.nerf.hierarchy import HierarchyChoice
from nerfexp.nerf.occupancy import OccupancyGrid, cell_corners, cell_indices, density_threshold
from nerfexp.nerf.volume_renderer import VolumeRenderer, padded_size, query_packed, query_thresholded
from tests.analytic import GaussianBlob, Slab, aimed_rays

BOX = [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]
NEAR, FAR = 2.0, 6.0
# density 50 over 0.5: T behind it is exp(-25), so every sample behind it could be left out
OPAQUE_SLAB = Slab(normal=(0.0, 0.0, 1.0), lower=-0.25, upper=0.25, density=50.0, colour=(0.1, 0.2, 0.9))


def trained_grid(field, resolution=16, updates=16, device="cpu", **options) -> OccupancyGrid:
    """A grid over BOX from ``field.density``: one warm-up update (every cell), then ``updates`` more,
    each re-evaluating a random quarter of the cells with the decaying memory of training's later steps;
    on ``device``."""
    grid = OccupancyGrid(resolution=resolution, update_every=1, warmup_steps=1, aabb=BOX, **options).to(device)
    torch.manual_seed(0)
    for step in range(updates + 1):
        grid.update(step, [field.density])
    return grid


def blob_density_range(blob: GaussianBlob, grid: OccupancyGrid) -> tuple[torch.Tensor, torch.Tensor]:
    """The exact smallest and largest density [R^3] of the blob in each cell: it falls off with the
    distance to the centre, largest at the cell's point nearest the centre, smallest at its farthest corner."""
    lower = grid.aabb[0] + cell_corners(grid.resolution) * grid.cell_size  # [R^3, 3]
    upper = lower + grid.cell_size
    centre = torch.tensor(blob.centre)
    nearest = torch.maximum(lower, torch.minimum(centre, upper))
    farthest = torch.where((centre - lower).abs() > (centre - upper).abs(), lower, upper)
    return blob.density(farthest), blob.density(nearest)


def test_cells_are_indexed_in_flat_order_and_outside_the_box_is_empty():
    # R = 4 over [-1, 1]^3: cells are 0.5 wide; (-0.9, 0.1, 0.6) is in cell (0, 2, 3) = (0 * 4 + 2) * 4 + 3 = 11
    index, inside = cell_indices(torch.tensor([[-0.9, 0.1, 0.6], [1.0, 0.0, 0.0], [0.0, -1.2, 0.0]]),
                                 torch.tensor(BOX), 4)
    assert index[0] == 11 and inside.tolist() == [True, False, False]  # the box is half-open: x = 1 is out
    grid = OccupancyGrid(resolution=4, aabb=BOX)
    assert grid.occupied_at(torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0]])).tolist() == [True, False]


def test_the_grid_marks_known_empty_cells_empty_and_known_solid_cells_occupied():
    blob = GaussianBlob(peak=5.0, radius=0.3)
    grid = trained_grid(blob)
    # sigma_t: 1 - exp(-sigma_t * diagonal) = 0.01 across a cell 2/16 wide: 0.0464; the mean estimate
    # (0.27: the blob's mass 5 (2 pi)^1.5 0.3^3 = 2.13 over the box's volume 8) is above it, so sigma_t decides
    sigma_t = density_threshold(0.01, math.sqrt(3) * 2 / 16)
    assert grid.density.mean() > sigma_t
    smallest, largest = blob_density_range(blob, grid)
    empty, solid = largest < sigma_t, smallest > sigma_t
    assert empty.sum() > 1500 and solid.sum() > 100  # of 4096 cells: both kinds are well represented
    assert not grid.occupied[empty].any() and grid.occupied[solid].all()

    slab = Slab(normal=(0.0, 0.0, 1.0), lower=-0.3, upper=0.2, density=3.0)
    grid = trained_grid(slab)
    z_lower = grid.aabb[0, 2] + cell_corners(16)[:, 2] * grid.cell_size[2]  # each cell's z extent
    z_upper = z_lower + grid.cell_size[2]
    inside, outside = (z_lower >= -0.3) & (z_upper <= 0.2), (z_upper <= -0.3) | (z_lower >= 0.2)
    assert grid.occupied[inside].all() and not grid.occupied[outside].any()


def test_a_new_grid_is_all_occupied_and_faint_fields_fall_back_to_the_mean():
    assert OccupancyGrid(resolution=8).occupied.all()  # nothing is skipped before the first update
    faint = GaussianBlob(peak=1e-3, radius=0.3)  # everywhere below sigma_t: the mean decides
    grid = trained_grid(faint, resolution=8)
    assert grid.occupied.any() and not grid.occupied.all()


def test_after_warm_up_a_quarter_of_the_cells_is_re_evaluated_and_decays():
    blob = GaussianBlob(peak=5.0, radius=0.3)
    grid = OccupancyGrid(resolution=8, update_every=2, warmup_steps=2, decay=0.5, aabb=BOX)
    grid.update(0, [blob.density])
    before = grid.density.clone()
    grid.update(1, [blob.density])  # not due
    assert torch.equal(grid.density, before)
    grid.update(2, [lambda x: torch.zeros(len(x))])  # the density went away: a quarter halves
    halved = torch.isclose(grid.density, before / 2) & (before > 0)
    assert halved.sum() == (before > 0).sum() // 4 or abs(int(halved.sum()) - int((before > 0).sum()) // 4) < 40
    assert (grid.density <= before).all()


def render_pair(field, grid, hierarchical=False, n=2048):
    """The same rays through ``field`` rendered without and with ``grid``, deterministic samples, float32, on the
    grid's device."""
    device = grid.density.device
    origins, directions = aimed_rays(n, torch.Generator().manual_seed(1), impact=1.2, distance=(3.5, 4.5))
    origins, directions = origins.float().to(device), directions.float().to(device)
    sampler = HierarchyChoice(hierarchical, n_coarse=64, n_fine=64, n_single=128)
    plain = VolumeRenderer(lambda: field, sampler, near=NEAR, far=FAR).to(device)
    fast = VolumeRenderer(lambda: field, sampler, near=NEAR, far=FAR, grid=grid).to(device)
    out = plain(origins, directions, deterministic=True), fast(origins, directions, deterministic=True)
    return out[0], out[1], fast.stats


@pytest.mark.parametrize("hierarchical", [False, True])
def test_skipping_empty_cells_changes_no_pixel_by_more_than_the_stated_tolerance(hierarchical, device):
    # The blob (peak 5, radius 0.3) absorbs 1 - exp(-5 * 0.3 sqrt(2 pi)) = 0.98 through its centre.
    # A cell is left out when its density estimate is below sigma_t, the density at which light crossing
    # it loses threshold = 1%. Stated tolerance: five such cells' worth, 1 - 0.99^5 = 0.049: a ray
    # meets the blob's faint edge (density sigma_t at 0.85 from the centre, 20x less at 1.15) on a few
    # cells on each side, and within one cell there the density varies up to 7.7x
    # (exp(2 * 0.85 * 0.2165 / (2 * 0.3^2)), the cell's diagonal 0.2165), which a jittered point
    # can underestimate.
    tolerance = 1 - 0.99**5
    blob = GaussianBlob(peak=5.0, radius=0.3)
    grid = trained_grid(blob, device=device, early_stop_transmittance=0.0)
    plain, fast, stats = render_pair(blob, grid, hierarchical)
    for name in plain:
        opacity = (plain[name]["opacity"] - fast[name]["opacity"]).abs()
        assert opacity.max() <= tolerance and opacity.mean() < 0.01, name  # on average under one cell's worth
        assert (plain[name]["rgb"] - fast[name]["rgb"]).abs().max() <= tolerance
    total = 128 if not hierarchical else 64 + 128
    assert stats["samples_per_ray"] < total / 3


def test_a_skipped_sample_is_a_sample_that_absorbs_nothing(device):
    # Independent of the grid's estimates: the accelerated render equals the plain render of a field
    # whose density is zeroed wherever the grid says empty (float32 rounding apart).
    blob = GaussianBlob(peak=5.0, radius=0.3)
    grid = trained_grid(blob, device=device, early_stop_transmittance=0.0)

    class Masked(GaussianBlob):
        def density(self, positions):
            return torch.where(grid.occupied_at(positions), super().density(positions), 0)

    plain, _, _ = render_pair(Masked(peak=5.0, radius=0.3), grid)
    _, fast, _ = render_pair(blob, grid)
    torch.testing.assert_close(fast["coarse"]["rgb"], plain["coarse"]["rgb"], atol=1e-6, rtol=0)


@pytest.mark.parametrize("eps", [1e-4, 1e-2, 0.1])
def test_early_termination_drops_at_most_the_threshold_of_colour(eps):
    # The opaque slab seen from above: without termination every sample behind it is evaluated for nothing.
    # Leaving out the runs of samples in front of which T < eps removes at most eps of absorbed light, so colour
    # and opacity move by <= eps.
    grid = OccupancyGrid(resolution=8, early_stop_transmittance=eps, segments=8, aabb=[[-4.0] * 3, [4.0] * 3])
    without = OccupancyGrid(resolution=8, early_stop_transmittance=0.0, aabb=[[-4.0] * 3, [4.0] * 3])
    _, reference, all_stats = render_pair(OPAQUE_SLAB, without)
    _, stopped, stats = render_pair(OPAQUE_SLAB, grid)
    colour = (reference["coarse"]["rgb"] - stopped["coarse"]["rgb"]).abs().max().item()
    opacity = (reference["coarse"]["opacity"] - stopped["coarse"]["opacity"]).abs().max().item()
    assert colour <= eps and opacity <= eps
    assert all_stats["samples_per_ray"] == 128  # the grid is all occupied: only termination leaves out
    assert stats["samples_per_ray"] < 0.8 * all_stats["samples_per_ray"]  # many samples lie behind the slab


@pytest.mark.parametrize("overrides", [["acceleration=occupancy"], ["experiment=fast"]])
def test_the_configured_grid_stops_no_ray_early(overrides):
    # Early termination is an option, off as configured (docs/acceleration.md says why): behind the opaque slab
    # every occupied sample is evaluated.
    with initialize_config_module("nerfexp.conf", version_base=None):
        node = compose("config", overrides=overrides).acceleration.grid
    configured = instantiate(node, resolution=8, aabb=[[-4.0] * 3, [4.0] * 3])
    _, _, stats = render_pair(OPAQUE_SLAB, configured)
    assert stats["samples_per_ray"] == 128  # every cell occupied before an update: all 128, none stopped


def test_the_warm_up_follows_a_falling_density_at_once_and_then_remembers():
    # An untrained field is dense everywhere (softplus(-1) = 0.31 with the default field), a trained one
    # empty: during the warm-up the estimate is the latest evaluation, so the grid empties as the field
    # does; afterwards max(decay * old, new) keeps what it saw.
    grid = OccupancyGrid(resolution=4, update_every=1, warmup_steps=2, decay=0.5, aabb=BOX)
    grid.update(0, [lambda x: torch.full((len(x),), 0.31)])
    assert grid.occupied.all()
    grid.update(1, [lambda x: torch.zeros(len(x))])  # still warming up: every cell empty at once
    assert torch.equal(grid.density, torch.zeros(64)) and not grid.occupied.any()
    grid.update(2, [lambda x: torch.full((len(x),), 8.0)])  # after the warm-up: a quarter of the cells, at 8
    seen = grid.density == 8.0
    assert seen.sum() == 16
    grid.update(3, [lambda x: torch.zeros(len(x))])  # those re-evaluated now halve, the others keep theirs
    assert set(grid.density[seen].tolist()) <= {8.0, 4.0} and (grid.density[seen] == 4.0).any()


def test_a_faint_density_floor_everywhere_leaves_empty_cells_empty():
    # A trained field's softplus density is never 0: the hash grid's coarse network keeps a faint floor in
    # empty space (on the glossy scene a median of about 0.005 where samples absorb almost nothing:
    # benchmarks/results/grid_skipping.md). With a
    # floor of 0.02 under sigma_t = 0.0464 (16 cells over BOX) and the blob's mean 0.27 + 0.02 above it,
    # the threshold is sigma_t: a cell is empty exactly where the blob adds less than sigma_t - 0.02.
    floor = 0.02
    blob = GaussianBlob(peak=5.0, radius=0.3)
    grid = trained_grid(SimpleNamespace(density=lambda x: blob.density(x) + floor))
    sigma_t = density_threshold(0.01, math.sqrt(3) * 2 / 16)
    smallest, largest = blob_density_range(blob, grid)
    empty, solid = largest + floor < sigma_t, smallest + floor > sigma_t
    assert empty.sum() > 1500 and solid.sum() > 100
    assert not grid.occupied[empty].any() and grid.occupied[solid].all()
    # a floor above sigma_t fills the box: the grid leaves nothing out
    assert trained_grid(SimpleNamespace(density=lambda x: blob.density(x) + 2 * sigma_t)).occupied.all()


def test_packed_sizes_are_few_per_doubling_and_less_than_an_eighth_above():
    sizes = [padded_size(n) for n in range(20000)]
    assert all(n <= p < n + max(n / 8, 1) for n, p in enumerate(sizes))
    assert sizes[:9] == list(range(9))  # small batches as they are
    for k in range(3, 14):  # the sizes from 2^k to 2^(k+1) - 1
        assert len({p for p in sizes if 2**k <= p < 2 ** (k + 1)}) == 8


def test_a_packed_batch_is_padded_with_kept_points_and_gives_each_kept_sample_its_own_answer():
    # A field whose colour is the position itself and whose density is its x: every kept sample's answer
    # is known, and a padded row that landed anywhere but the end would show
    seen = []

    class Positional(torch.nn.Module):
        def forward(self, points, viewdirs):
            seen.append((points.clone(), viewdirs.clone()))
            return FieldOutputs(rgb=points * 2, sigma=points[:, 0])

    generator = torch.Generator().manual_seed(0)
    points, viewdirs = torch.randn(7, 40, 3, generator=generator), torch.randn(7, 3, generator=generator)
    keep = torch.rand(7, 40, generator=generator) < 0.6
    rgb, sigma, penalties = query_packed(Positional(), points, viewdirs, keep)
    n = int(keep.sum())
    assert len(seen) == 1 and len(seen[0][0]) == padded_size(n) > n  # 170 kept, padded to 176
    batch, dirs = seen[0]
    torch.testing.assert_close(batch[n:], batch[: padded_size(n) - n])  # the padding: kept points again
    torch.testing.assert_close(dirs[n:], dirs[: padded_size(n) - n])
    torch.testing.assert_close(rgb, torch.where(keep[..., None], points * 2, 0), rtol=0, atol=0)
    torch.testing.assert_close(sigma, torch.where(keep, points[..., 0], 0), rtol=0, atol=0)
    assert penalties is None  # none answered, none made up


def blob_alphas(blob, origins, directions, out):
    """The alpha 1 - exp(-sigma delta) [B, S] of each sample of a render ``out`` of rays ``origins``,
    ``directions`` [B, 3] through ``blob``, from its density at the samples (float64: independent of the
    renderer's arithmetic)."""
    t_starts, t_ends = out["t_starts"].double(), out["t_ends"].double()
    points = origins.double()[:, None] + directions.double()[:, None] * t_starts[..., None]
    lengths = torch.linalg.vector_norm(directions.double(), dim=-1)[:, None]
    return -torch.expm1(-blob.density(points) * (t_ends - t_starts) * lengths)


@pytest.mark.parametrize("threshold", [1e-3, 1e-2, 0.05])
def test_an_alpha_threshold_colours_exactly_the_samples_above_it_and_moves_a_pixel_by_no_more_than_it_implies(
        threshold):
    # Every cell occupied (a new grid, no update), no early termination: the threshold alone leaves samples out.
    # A sample left out absorbs nothing, so the render moves by at most the share of light the left-out samples
    # absorbed in the full render (the sum of their weights): the light they took now goes on to later
    # samples or the background, and a colour in [0, 1] moves by at most that share. Each left-out sample has
    # alpha below the threshold, so the share is also at most 1 - (1 - threshold)^(number left out).
    blob = GaussianBlob(peak=5.0, radius=0.3)
    box = [[-4.0] * 3, [4.0] * 3]
    plain, thresholded, stats = render_pair(blob, OccupancyGrid(resolution=4, early_stop_transmittance=0.0, aabb=box))
    _, thresholded, stats = render_pair(blob, OccupancyGrid(resolution=4, early_stop_transmittance=0.0, aabb=box,
                                                            alpha_threshold=threshold))
    origins, directions = aimed_rays(2048, torch.Generator().manual_seed(1), impact=1.2, distance=(3.5, 4.5))
    alpha = blob_alphas(blob, origins, directions, plain["coarse"])
    left_out = alpha < threshold
    assert stats["samples_per_ray"] == 128  # every density evaluated
    expected = (~left_out).sum().item() / 2048  # the colour head: exactly the samples at or above the threshold
    assert stats["colour_samples_per_ray"] == pytest.approx(expected, abs=1.5 / 2048)  # float32 ties: a sample
    share = (plain["coarse"]["weights"].double() * left_out).sum(-1)  # [B]
    moved = (plain["coarse"]["rgb"] - thresholded["coarse"]["rgb"]).abs().amax(-1).double()
    assert (moved <= share + 1e-6).all()
    assert (share <= 1 - (1 - threshold) ** left_out.sum(-1) + 1e-9).all()
    assert moved.max() > 0  # something was left out: the test can fail
    # the samples left out absorb nothing: the weights there are exactly 0
    assert (thresholded["coarse"]["weights"][alpha < threshold * 0.99] == 0).all()


def test_alpha_threshold_query_colours_the_samples_at_or_above_it_and_zeroes_the_others():
    # query_thresholded alone, against alphas computed here: the slab's density 3 over intervals of 0.1 and
    # 0.001 gives alpha 0.259 and 0.003; threshold 0.01 keeps exactly the long intervals inside the slab
    slab = Slab(normal=(0.0, 0.0, 1.0), lower=-0.5, upper=0.5, density=3.0, colour=(0.1, 0.2, 0.9))
    generator = torch.Generator().manual_seed(0)
    points = torch.rand(6, 30, 3, generator=generator, dtype=torch.float64) * 2 - 1  # half in the slab
    long = torch.rand(6, 30, generator=generator) < 0.5
    lengths = torch.where(long, 0.1, 0.001).double()
    keep = torch.rand(6, 30, generator=generator) < 0.8
    outputs, coloured = query_thresholded(slab, points, torch.zeros(6, 3, dtype=torch.float64), keep, lengths, 0.01)
    inside = slab.density(points) > 0
    chosen = keep & inside & long
    assert coloured == chosen.sum() > 0 and (keep & inside & ~long).any()
    torch.testing.assert_close(outputs.sigma, torch.where(chosen, 3.0, 0.0).double(), rtol=0, atol=0)
    torch.testing.assert_close(outputs.rgb, torch.where(chosen[..., None], torch.tensor([0.1, 0.2, 0.9], dtype=torch.float64),
                                                        0.0), rtol=0, atol=0)


def test_march_steps_measure_the_threshold_over_a_step_of_the_box_diagonal():
    # BOX's diagonal 2 sqrt(3) = 3.464 over 64 steps: 0.05413; sigma_t = -log(0.99) / 0.05413 = 0.18568, against
    # 0.04642 over the diagonal of a cell 2/16 wide. A slab of density 0.1 lies between the two: occupied over
    # the cell's diagonal, empty over a step.
    grid = OccupancyGrid(resolution=16, aabb=BOX, march_steps=64)
    assert grid.cell_thresholds() == pytest.approx(0.18568, rel=1e-4)
    assert OccupancyGrid(resolution=16, aabb=BOX).cell_thresholds() == pytest.approx(0.046421, rel=1e-4)
    # A small dense blob far from the slab's cells at x < -0.5 keeps the mean estimate (0.4: its mass
    # 200 (2 pi)^1.5 0.1^3 = 3.1 over the box's volume 8) above both sigma_t, so sigma_t decides.
    faint = Slab(normal=(0.0, 0.0, 1.0), lower=-0.25, upper=0.25, density=0.1)
    blob = GaussianBlob(centre=(0.7, 0.7, 0.7), peak=200.0, radius=0.1)
    field = SimpleNamespace(density=lambda x: faint.density(x) + blob.density(x))
    z_lower = -1 + cell_corners(16)[:, 2] * 2 / 16
    x_upper = -1 + (cell_corners(16)[:, 0] + 1) * 2 / 16
    slab_cells = (z_lower >= -0.25) & (z_lower + 2 / 16 <= 0.25) & (x_upper <= -0.5)
    assert slab_cells.sum() == 4 * 16 * 4  # 4 layers in z, 16 in y, 4 in x
    assert trained_grid(field).occupied[slab_cells].all()
    stepped = trained_grid(field, march_steps=64)
    assert stepped.density.mean() > stepped.cell_thresholds()
    assert not stepped.occupied[slab_cells].any() and stepped.occupied.any()


def test_update_occupied_re_evaluates_the_occupied_cells_besides_a_random_quarter():
    # Four occupied cells of 512 (a cube 0.5 wide at a corner of 4 cells 0.25 wide, R = 8 over BOX): after the
    # warm-up, a quarter (128) at random and 128 draws from the 4 occupied cells. Each occupied cell escapes
    # both with probability 0.75 (3/4)^128 < 1e-16: the density gone, all four halve at once.
    cube = SimpleNamespace(density=lambda x: torch.where((x > 0.5).all(-1), 5.0, 0.0))
    grid = OccupancyGrid(resolution=8, update_every=1, warmup_steps=1, decay=0.5, aabb=BOX, update_occupied=True)
    torch.manual_seed(0)
    grid.update(0, [cube.density])
    occupied = grid.occupied.clone()
    assert occupied.sum() == 8  # x, y, z > 0.5: 2 cells per axis of 0.25
    before = grid.density.clone()
    grid.update(1, [lambda x: torch.zeros(len(x))])
    assert torch.equal(grid.density[occupied], before[occupied] / 2)
    cells = grid.cells_to_update(2)
    assert len(cells) == len(torch.unique(cells)) <= 128 + 128
    # without it, the 8 occupied cells are among a random quarter only: some keep their density
    plain = OccupancyGrid(resolution=8, update_every=1, warmup_steps=1, decay=0.5, aabb=BOX)
    torch.manual_seed(0)
    plain.update(0, [cube.density])
    plain.update(1, [lambda x: torch.zeros(len(x))])
    assert (plain.density[occupied] == before[occupied]).any()
    assert len(plain.cells_to_update(2)) == 128


def test_update_fraction_is_the_share_of_cells_each_update_re_evaluates_after_the_warm_up():
    # R = 8: 512 cells; every one in the warm-up, then an eighth (64) distinct cells at random; the density
    # gone at step 1, exactly those 64 cells halve (decay 0.5) and the other 448 keep theirs
    grid = OccupancyGrid(resolution=8, update_every=1, warmup_steps=1, decay=0.5, aabb=BOX, update_fraction=0.125)
    assert len(grid.cells_to_update(0)) == 512
    grid.update(0, [lambda x: torch.ones(len(x))])
    grid.update(1, [lambda x: torch.zeros(len(x))])
    assert (grid.density == 0.5).sum() == 64 and (grid.density == 1.0).sum() == 448
    with pytest.raises(ValueError, match="acceleration.grid.update_fraction: expected"):
        OccupancyGrid(update_fraction=0.0)
