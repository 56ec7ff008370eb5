"""Ray marching through the occupancy grid (``nerfexp.nerf.marching``, ``sampler=march``): its steps against the
cells' geometry worked out in float64, its fused kernel against the torch path, and its renders against analytic
fields whose opacity is known in closed form."""

import math

import pytest
import torch
from hydra import compose, initialize_config_module

from nerfexp.errors import ConfigError
from nerfexp.kernels import kernel
from nerfexp.nerf.contraction import SceneContraction
from nerfexp.nerf.marching import GridMarchSampler, March, Marched, march_fixed, march_growing, march_rays, spans_of
from nerfexp.nerf.occupancy import OccupancyGrid, cell_corners
from nerfexp.nerf.volume_renderer import VolumeRenderer
from nerfexp.settings.checks import check_settings
from tests.analytic import Slab, aimed_rays

BOX = [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]
NEAR, FAR = 2.0, 6.0


def random_rays(n: int, seed: int) -> tuple[torch.Tensor, ...]:
    """``n`` float32 rays from around the box towards it and past it, with the cases a march must get right: rays
    parallel to an axis (inside and outside the box's slab), rays that miss the box, and a ray of zero direction."""
    generator = torch.Generator().manual_seed(seed)
    origins = torch.randn(n, 3, generator=generator) * 3
    targets = (torch.rand(n, 3, generator=generator) - 0.5) * 2.4  # most rays cross the box; none of unit length
    directions = (targets - origins) * (0.5 + torch.rand(n, 1, generator=generator))
    directions[:4, 1] = 0  # parallel to the y faces
    origins[:2, 1] = 0.5  # inside their slab
    origins[2:4, 1] = 3.0  # outside it: no step inside the box
    directions[4] = 0
    near, far = torch.full((n,), 0.1), torch.full((n,), 9.0)
    offsets = torch.rand(n, generator=generator)
    return origins, directions, near, far, offsets


def random_grid(resolution: int, share: float, seed: int) -> torch.Tensor:
    return torch.rand(resolution**3, generator=torch.Generator().manual_seed(seed)) < share


def fused_march(march: March, origins, directions, near, far, offsets) -> Marched:
    """The kernel's march (the test needs it built: nerfexp builds it on every machine with a compiler)."""
    built = kernel("grid_march")
    assert built is not None, "the grid_march kernel could not be built here"
    return march_rays(march, origins, directions, near, far, offsets)


@pytest.mark.parametrize("cone_angle", [0.0, 0.03])
@pytest.mark.parametrize("max_samples", [1, 7, 1000])
def test_the_kernel_keeps_the_torch_paths_steps_bit_for_bit(cone_angle, max_samples):
    occupied = random_grid(12, 0.3, seed=1)
    aabb = torch.tensor([[-1.5, -1.2, -1.0], [1.5, 1.3, 1.1]])
    march = March(occupied, 12, aabb, step=0.03, cone_angle=cone_angle, max_samples=max_samples, contraction=None)
    rays = random_rays(600, seed=2)
    torch_path = march_fixed if march.fixed else march_growing
    expected = Marched(*torch_path(march, *rays))
    got = fused_march(march, *rays)
    assert (expected.counts > 0).sum() > 300  # the rays do cross occupied cells
    for name in Marched._fields:
        assert torch.equal(getattr(got, name), getattr(expected, name)), name
    assert got.counts.max() <= max_samples
    assert got.counts[2:5].sum() == 0  # parallel outside the box's slab, and a ray of no direction


def test_with_a_contraction_the_kernel_keeps_the_torch_paths_steps_but_where_a_midpoint_rounds_to_another_cell():
    # The contraction's square root rounds differently in the two (torch's float32 sqrt is not correctly rounded on
    # every CPU): a midpoint within a rounding error of a cell's face may land in the neighbouring cell.
    contraction = SceneContraction(centre=[0.1, -0.2, 0.0], radius=0.8)
    occupied = random_grid(16, 0.2, seed=3)
    march = March(occupied, 16, contraction.box, step=0.05, cone_angle=1 / 64, max_samples=1000,
                  contraction=contraction)
    origins, directions, near, _, offsets = random_rays(400, seed=4)
    far = torch.full_like(near, 60.0)
    expected = Marched(*march_growing(march, origins, directions, near, far, offsets))
    got = fused_march(march, origins, directions, near, far, offsets)
    assert expected.t_starts.numel() > 1000
    differing = (got.counts != expected.counts).sum().item()
    assert differing <= 2, differing


def cell_span(origins: torch.Tensor, directions: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor):
    """Where rays o + t d are inside the box [lower, upper]: (enter, leave) [B] in float64 (the slab method)."""
    o, d = origins.double(), directions.double()
    with torch.no_grad():
        t_a, t_b = (lower.double() - o) / d, (upper.double() - o) / d
    return torch.minimum(t_a, t_b).amax(-1), torch.maximum(t_a, t_b).amin(-1)


@pytest.mark.parametrize("use_kernel", [True, False])
def test_a_step_is_kept_exactly_where_its_midpoint_lies_in_the_one_occupied_cell(use_kernel, monkeypatch):
    # One occupied cell of a 4^3 grid over [-1, 1]^3: cell (2, 1, 3) = [0, 0.5] x [-0.5, 0] x [0.5, 1]. Worked out
    # in float64 from the cell's faces: a step [a, b] is kept iff its midpoint's t lies strictly inside the ray's
    # span through the cell (midpoints within 1e-5 of a face are left out of the comparison: rounding decides them).
    if not use_kernel:
        monkeypatch.setenv("NERFEXP_KERNELS", "off")
    resolution, cell = 4, (2, 1, 3)
    occupied = torch.zeros(resolution**3, dtype=torch.bool)
    occupied[(cell[0] * resolution + cell[1]) * resolution + cell[2]] = True
    march = March(occupied, resolution, torch.tensor(BOX), step=0.01, cone_angle=0.0, max_samples=10_000,
                  contraction=None)
    generator = torch.Generator().manual_seed(5)
    target = torch.tensor([0.25, -0.25, 0.75]) + (torch.rand(300, 3, generator=generator) - 0.5) * 0.6
    origins = torch.randn(300, 3, generator=generator) * 2 + torch.tensor([0.0, 0.0, 3.0])
    directions = target - origins
    near, far = torch.zeros(300), torch.full((300,), 3.0)
    offsets = torch.rand(300, generator=generator)
    marched = march_rays(march, origins, directions, near, far, offsets)
    lower = torch.tensor([0.0, -0.5, 0.5])
    enter, leave = cell_span(origins, directions, lower, lower + 0.5)
    base = (0.01 / torch.linalg.vector_norm(directions.double(), dim=-1))
    kept_rays = torch.repeat_interleave(torch.arange(300), marched.counts)
    box_enter, box_leave = cell_span(origins, directions, torch.tensor(BOX[0]), torch.tensor(BOX[1]))
    k = torch.arange(2000, dtype=torch.float64)
    for r in range(300):
        starts = box_enter[r].clamp_min(0) + (k + float(offsets[r])) * base[r]  # every step, the last cut at the box
        starts = starts[starts < box_leave[r]]
        mids = 0.5 * (starts + torch.clamp(starts + base[r], max=box_leave[r]))
        clear = ((mids - enter[r]).abs() > 1e-4) & ((mids - leave[r]).abs() > 1e-4)
        expected = mids[(mids > enter[r]) & (mids < leave[r]) & clear]
        got = 0.5 * (marched.t_starts[kept_rays == r] + marched.t_ends[kept_rays == r]).double()
        assert all((got - mid).abs().min() < 1e-4 for mid in expected), r  # each step inside the cell is kept
        assert ((got > enter[r] - 1e-4) & (got < leave[r] + 1e-4)).all(), r  # and none outside it
    assert marched.counts.gt(0).float().mean() > 0.5  # most rays aimed at the cell do cross it


def test_spans_hold_each_rays_steps_first_and_empty_steps_at_far_after_them():
    marched = Marched(t_starts=torch.tensor([1.0, 2.0, 3.0, 4.5]), t_ends=torch.tensor([1.5, 2.5, 3.5, 5.0]),
                      counts=torch.tensor([3, 0, 1]))
    spans = spans_of(marched, torch.tensor([9.0, 8.0, 7.0]))
    assert spans.valid.tolist() == [[True, True, True], [False, False, False], [True, False, False]]
    assert spans.t_starts.tolist() == [[1.0, 2.0, 3.0], [8.0, 8.0, 8.0], [4.5, 7.0, 7.0]]
    assert spans.t_ends.tolist() == [[1.5, 2.5, 3.5], [8.0, 8.0, 8.0], [5.0, 7.0, 7.0]]
    empty = spans_of(Marched(torch.zeros(0), torch.zeros(0), torch.zeros(2, dtype=torch.long)), torch.ones(2))
    assert empty.valid.shape == (2, 1) and not empty.valid.any()


def slab_grid(slab: Slab, resolution: int) -> OccupancyGrid:
    """A grid over BOX whose occupied cells are exactly those the slab (normal z) passes through."""
    grid = OccupancyGrid(resolution=resolution, aabb=BOX)
    lower = grid.aabb[0] + cell_corners(resolution) * grid.cell_size  # [R^3, 3]
    upper = lower + grid.cell_size
    grid.occupied.copy_((upper[:, 2] > slab.lower) & (lower[:, 2] < slab.upper))
    return grid


@pytest.mark.parametrize("n_steps", [256, 1024])
def test_a_marched_slab_absorbs_what_the_closed_form_says_within_a_steps_worth_at_each_face(n_steps):
    # A slab of density 4 between z = -0.25 and 0.25 inside the box, seen from above. The march's quadrature
    # differs from the closed form only in the two steps cut by the slab's faces: at most sigma dt of optical depth
    # each, so the opacity is within 1 - exp(-2 sigma dt) of the truth (dt: each ray's step in distance).
    slab = Slab(normal=(0.0, 0.0, 1.0), lower=-0.25, upper=0.25, density=4.0)
    grid = slab_grid(slab, 8)
    renderer = VolumeRenderer(lambda: slab, lambda: GridMarchSampler(n_steps=n_steps), near=NEAR, far=FAR, grid=grid)
    origins, directions = aimed_rays(512, torch.Generator().manual_seed(6), impact=0.5, distance=(3.5, 4.5),
                                     cone_degrees=40)
    out = renderer(origins.float(), directions.float(), deterministic=False)["coarse"]
    truth, _ = slab.opacity_and_depth(origins, directions, NEAR, FAR)
    dt = math.sqrt(12) / n_steps  # the box's diagonal / n_steps; unit directions
    error = (out["opacity"].double() - truth).abs()
    assert error.max() <= 1 - math.exp(-2 * 4.0 * dt) + 1e-6
    assert truth.min() > 0.8  # every ray crosses the slab
    # the samples lie where the slab is: the occupied cells' layer, two cells of 0.25 thick, about 0.5 / dt
    # steps per ray along its slanted path, never the 6 / dt between near and far
    assert renderer.stats["samples_per_ray"] < 1.1 * 0.5 / math.cos(math.radians(40)) / dt


def test_a_batch_that_finds_no_occupied_cell_renders_the_background_with_zero_gradients():
    slab = Slab(normal=(0.0, 0.0, 1.0), lower=-0.25, upper=0.25, density=4.0)
    grid = OccupancyGrid(resolution=4, aabb=BOX)
    grid.occupied.zero_()
    field = torch.nn.Linear(3, 4)  # a network whose gradients can be looked at

    def network(points, directions):
        from nerfexp.nerf.fields import FieldOutputs
        out = field(points)
        return FieldOutputs(rgb=torch.sigmoid(out[..., :3]), sigma=torch.nn.functional.softplus(out[..., 3]))

    renderer = VolumeRenderer(lambda: network, lambda: GridMarchSampler(), near=NEAR, far=FAR, grid=grid)
    origins, directions = aimed_rays(64, torch.Generator().manual_seed(7), impact=0.5, distance=(3.5, 4.5))
    out = renderer(origins.float(), directions.float(), deterministic=False)["coarse"]
    assert torch.equal(out["rgb"], torch.ones(64, 3))  # white, the renderer's default background
    assert torch.equal(out["opacity"], torch.zeros(64))
    loss = ((out["rgb"] - 0.5) ** 2).mean()
    assert torch.isfinite(loss)
    if loss.requires_grad:
        loss.backward()
        assert all(p.grad is None or torch.equal(p.grad, torch.zeros_like(p)) for p in field.parameters())
    assert renderer.stats["samples_per_ray"] == 0
    del slab


def test_the_sampler_without_an_occupancy_grid_is_refused_before_any_work():
    with initialize_config_module("nerfexp.conf", version_base=None):
        cfg = compose("config", overrides=["sampler=march"])
        with pytest.raises(ConfigError, match="acceleration=occupancy"):
            check_settings(cfg)
        check_settings(compose("config", overrides=["sampler=march", "acceleration=occupancy"]))
    with pytest.raises(ValueError, match="acceleration=occupancy"):
        VolumeRenderer(lambda: Slab(), lambda: GridMarchSampler(), near=NEAR, far=FAR)


def test_a_batchs_memory_is_estimated_at_max_samples_per_ray():
    # 4096 rays x 4096 samples through the paper's 8 layers of 256: 4096 * 4096 * 256 * 8 * 4 bytes kept for the
    # backward pass = 128 GiB, more than a CPU machine here has; 256 samples fit.
    with initialize_config_module("nerfexp.conf", version_base=None):
        paper = ["sampler=march", "acceleration=occupancy", "scale=paper"]
        with pytest.raises(ConfigError, match="max_samples"):
            check_settings(compose("config", overrides=[*paper, "sampler.max_samples=4096"]))
        check_settings(compose("config", overrides=paper))
