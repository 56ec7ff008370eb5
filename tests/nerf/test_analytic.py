"""Analytic fields against independent truth, then the renderer's quadrature against the fields.

How fast the renderer should converge, worked out before measuring. N samples per ray, h = (far - near) / N.

Stratified, deterministic: the samples sit at bin midpoints t_i = near + (i + 1/2) h, and each stands for
[t_i, t_{i+1}] (``nerfexp.nerf.sampling.intervals``; the last ends at far, so it is h/2 long). The optical
depth in front of sample i, h sum_{j<i} sigma(t_j), is the midpoint rule for tau(t_i - h/2), so
T_i ~ T(t_i - h/2) and the weight T_i (1 - exp(-sigma_i h)) is the light stopped in [t_i - h/2, t_i + h/2],
the bin whose midpoint t_i is: a left-endpoint rule on a grid of midpoints is the midpoint rule on the
bins, except that the last sample stands for h/2 only. Hence (Euler-Maclaurin)
tau_hat - tau = -(h^2 / 24) (sigma'(far) - sigma'(near)) - (h / 2) sigma(far) + O(h^4):
  - a smooth density that vanishes at both ends (a Gaussian blob well inside [near, far]): every
    Euler-Maclaurin term vanishes, and the total optical depth, so the opacity, converges faster than any
    power of h; by Poisson summation its error is at most 2 tau exp(-2 pi^2 r^2 / h^2) (r the blob's
    radius). The depth sums the weights against t, which uses the optical depths up to interior points,
    midpoint sums over part of the blob: second order;
  - sigma(near) > 0 = sigma(far) (a blob cut by near): second order, opacity error (h^2 / 24) sigma'(near) T(far);
  - sigma(far) > 0 (a blob cut by far): first order, opacity error -(h / 2) sigma(far) T(far);
  - a step in the density (slab, shell): the midpoint rule moves each surface to the nearest bin edge, by
    up to h/2: first order, for opacity and depth alike, in the mean over random placements of the
    surfaces relative to the sample grid (for one placement the error is not even monotone in N).
Stratified with jitter (a uniform sample in each bin): for a smooth density each bin's error is O(h^2),
independent of the others' and of zero mean to leading order, so their sum spreads as sqrt(N) h^2 ~ h^(3/2):
order 3/2 for the mean absolute error over rays. A step: first order, as above.
Hierarchical: the coarse and fine samples merged are not evenly spaced (fine samples are evenly spaced
within each coarse interval, at a density proportional to its dilated weight). The left-endpoint rule's
error, -(1/2) int sigma'(t) Delta(t) dt for a local spacing Delta, cancels to the midpoint rule only for an
even spacing, so every quantity of every field is first order in N = n_coarse + n_fine (n_coarse = N / 4
here, the fine pass's samples per ray), once the coarse samples resolve the field; its constant is set by
the spacing where the light stops, small for surfaces, which is what hierarchical sampling is for.
A single-colour field's colour error is |c - background| times its opacity error, so it has the same order.
"""

import math

import pytest
import torch

from nerfexp.nerf.backgrounds import BACKGROUNDS
from nerfexp.nerf.hierarchy import HierarchyChoice
from nerfexp.nerf.volume_renderer import VolumeRenderer
from tests.analytic import GaussianBlob, Shell, Slab, aimed_rays, cost_for_error, render_errors, segments_truth

NEAR, FAR = 2.0, 6.0
WHITE = BACKGROUNDS["white"]


def ray(origin, direction):
    """One float64 ray as ([1, 3], [1, 3]), its direction normalised."""
    o, d = torch.tensor([origin], dtype=torch.float64), torch.tensor([direction], dtype=torch.float64)
    return o, d / d.norm(dim=-1, keepdim=True)


def brute_force(field, origin, direction, near, far, n=1_000_001):
    """Opacity and depth of one ray [3], [3] from the field's own sigma at n points, float64: tau by the
    cumulative trapezoid rule, T = exp(-tau), and the depth by its definition int t p / int p, p = sigma T
    (not the by-parts forms the fields use)."""
    t = torch.linspace(near, far, n, dtype=torch.float64)
    sigma = field(origin + t[:, None] * direction, direction[None]).sigma
    tau = torch.cat([torch.zeros(1, dtype=torch.float64), torch.cumulative_trapezoid(sigma, t)])
    p = sigma * torch.exp(-tau)
    mass = torch.trapezoid(p, t)
    depth = torch.trapezoid(t * p, t) / mass if mass > 0 else torch.tensor(far)
    return -torch.expm1(-tau[-1]).item(), depth.item()


SLAB, SHELL, BLOB = Slab(), Shell(), GaussianBlob()  # |z| < 0.5 at 3; radius 1, 0.1 thick at 10; r = 0.3, peak 5
FIELD_RAYS = {  # field, density steps a ray can cross (None: smooth), rays as (origin, direction)
    "slab": (SLAB, 2, [((0, 0, 4), (0, 0, -1)),  # straight through
                       ((1, 0, 4), (-0.3, 0.1, -1)),  # obliquely
                       ((0, 0, 2.3), (0, 0, -1)),  # starts inside (z = 0.3 at near)
                       ((0, 0, 6.3), (0, 0, -1)),  # leaves after far
                       ((0, 0, 0.3), (1, 0, 0)),  # parallel to the planes, inside them
                       ((0, 0, 4), (1, 0, 0)),  # parallel, outside: a miss
                       ((0, 0, 4), (0, 0.2, 1))]),  # away from it: a miss
    "shell": (SHELL, 4, [((0, 0, 4), (0, 0, -1)),  # through the centre: two segments
                         ((0.5, 0, 4), (0, 0, -1)),  # two segments, longer
                         ((0.999, 0, 4), (0, 0, -1)),  # grazes the inner sphere: two long segments
                         ((1.05, 0, 4), (0, 0, -1)),  # misses the inner sphere: one segment
                         ((1.1, 0, 4), (0, 0, -1)),  # tangent to the outer sphere: nothing
                         ((2, 0, 4), (0, 0, -1)),  # a miss
                         ((0, 0, 3.05), (0, 0, -1)),  # starts inside the wall
                         ((0, 0, 2), (0, 0, -1))]),  # starts in the hollow
    "blob": (BLOB, None, [((0, 0, 4), (0, 0, -1)),  # through the centre
                          ((0.3, 0.2, 4), (0, 0, -1)),  # off centre
                          ((2, 0, 4), (0, 0, -1)),  # far off: opacity 1e-9
                          ((0, 0, 2.1), (0, 0, -1)),  # starts inside
                          ((0, 0, 5.5), (0, 0, -1)),  # cut by far
                          ((-2.4, 0, 3.2), (0.6, 0, -0.8))]),  # obliquely
}


@pytest.mark.parametrize("name", FIELD_RAYS)
def test_truth_matches_brute_force_integration_of_the_fields_own_density(name):
    field, steps, rays = FIELD_RAYS[name]
    h = (FAR - NEAR) / (1_000_001 - 1)
    for origin, direction in rays:
        o, d = ray(origin, direction)
        truth = field.truth(o, d, NEAR, FAR)
        opacity, depth = brute_force(field, o[0], d[0], NEAR, FAR)
        if opacity == 0:  # no density on the ray at all: both report far
            assert truth["opacity"].item() == 0 and truth["depth"].item() == FAR, (origin, direction)
            continue
        if steps is None:
            # Smooth integrands: the trapezoid rule's error, h^2 / 12 (f'(far) - f'(near)), is below 1e-10.
            opacity_tol, depth_tol = 1e-9, 1e-9
        else:
            # The trapezoid cell that holds a step in a density s gets up to s h / 2 too much or too little
            # optical depth, and the absorbed mass moves by as much, within t in [near, far]: so the opacity
            # is off by at most steps * s h / 2, and depth * opacity by at most steps * s h (far - near).
            opacity_tol = steps * field.sigma * h / 2
            depth_tol = steps * field.sigma * h * (FAR - NEAR) / opacity
        assert abs(truth["opacity"].item() - opacity) <= opacity_tol, (origin, direction)
        assert abs(truth["depth"].item() - depth) <= depth_tol, (origin, direction)
        colour = torch.tensor(field.colour, dtype=torch.float64)
        torch.testing.assert_close(truth["rgb"][0], opacity * colour + (1 - opacity) * torch.ones(3).double(),
                                   atol=opacity_tol, rtol=0)


def test_segment_truth_hand_worked_cases():
    s = 3.0
    # One segment [3.5, 4.5]: an exponential entering at 3.5, cut at length 1 (as in
    # tests/nerf/test_volume_renderer.py).
    opacity, depth = segments_truth(torch.tensor([[3.5]]).double(), torch.tensor([[4.5]]).double(), s, NEAR, FAR)
    assert math.isclose(opacity.item(), -math.expm1(-s), rel_tol=1e-15)
    assert math.isclose(depth.item(), 3.5 + 1 / s - math.exp(-s) / -math.expm1(-s), rel_tol=1e-15)
    # Two segments, as a mixture of the one-segment answers: the second is entered with T = exp(-s / 2).
    starts, ends = torch.tensor([[2.5, 5.0]]).double(), torch.tensor([[3.0, 5.5]]).double()
    opacity, depth = segments_truth(starts, ends, s, NEAR, FAR)
    one = [segments_truth(starts[:, k:k + 1], ends[:, k:k + 1], s, NEAR, FAR) for k in range(2)]
    mass = [one[0][0].item(), math.exp(-s / 2) * one[1][0].item()]
    assert math.isclose(opacity.item(), sum(mass), rel_tol=1e-15)
    assert math.isclose(depth.item(), (mass[0] * one[0][1].item() + mass[1] * one[1][1].item()) / sum(mass),
                        rel_tol=1e-15)
    cases = [  # density, starts, ends, opacity, depth (None: not checked)
        (1e-6, [[3.0]], [[5.0]], -math.expm1(-2e-6), 4.0 - 2e-6 / 6),  # faint: 3 + 2 (1/2 - tau/12 + O(tau^3))
        (1e9, [[3.0]], [[5.0]], 1.0, 3.0 + 1e-9),  # dense: stops at its entry, 1 / s in
        (s, [[-math.inf]], [[math.inf]], -math.expm1(-4 * s), None),  # infinite, clipped to [near, far]
        (s, [[1.0, 7.0]], [[1.5, 9.0]], 0.0, FAR),  # both outside [near, far]: nothing
        (s, [[3.0]], [[3.0]], 0.0, FAR),  # empty
    ]
    for density, a, b, want_opacity, want_depth in cases:
        opacity, depth = segments_truth(torch.tensor(a).double(), torch.tensor(b).double(), density, NEAR, FAR)
        assert math.isclose(opacity.item(), want_opacity, rel_tol=1e-9)
        assert torch.isfinite(depth).all() and NEAR <= depth.item() <= FAR
        if want_depth is not None:
            assert math.isclose(depth.item(), want_depth, rel_tol=1e-9)


def test_blob_depth_quadrature_is_converged():
    # The blob's depth integrates 1 - T by Gauss-Legendre: halving the panels changes nothing that
    # matters, for rays through the blob, grazing it, starting inside it and cut by far.
    origins, directions = aimed_rays(64, torch.Generator().manual_seed(0), impact=0.9, distance=(1.5, 6.5))
    depth = BLOB.truth(origins, directions, NEAR, FAR)["depth"]
    finer = GaussianBlob(panels=2 * BLOB.panels).truth(origins, directions, NEAR, FAR)["depth"]
    assert (finer - depth).abs().max() < 1e-10
    coarse = GaussianBlob(panels=2).truth(origins, directions, NEAR, FAR)["depth"]
    assert (coarse - depth).abs().max() > 1e-6  # the check can fail: 2 panels of 8 nodes are not enough


def render(field, origins, directions, n, hierarchical, deterministic=True, n_coarse=None):
    """The final output of the renderer with n samples per ray: n stratified, or n_coarse (n / 4 unless
    given) coarse and n - n_coarse fine; and its network evaluations per ray."""
    n_coarse = n // 4 if n_coarse is None else n_coarse
    renderer = VolumeRenderer(lambda: field, HierarchyChoice(hierarchical, n_coarse, n - n_coarse, n), NEAR, FAR)
    out = renderer(origins, directions, deterministic=deterministic)
    return out["fine" if hierarchical else "coarse"], renderer.evaluations_per_ray


def observed_order(ns, errors):
    """Least-squares slope p of log(error) = c - p log(N)."""
    x, y = torch.tensor(ns, dtype=torch.float64).log(), torch.tensor(errors, dtype=torch.float64).log()
    x = x - x.mean()
    return -((x * (y - y.mean())).sum() / (x * x).sum()).item()


def convergence(field, rays, ns, hierarchical, deterministic):
    """Errors (``render_errors``) of each quantity at each N: {quantity: [error per N]}."""
    truth = field.truth(*rays, NEAR, FAR, WHITE)
    errors = [render_errors(render(field, *rays, n, hierarchical, deterministic)[0], truth) for n in ns]
    return {key: [e[key] for e in errors] for key in errors[0]}


def blob_rays(distance, n=128, seed=0):
    """Rays through the blob (impact up to 2 r), its centre at ``distance`` along them."""
    return aimed_rays(n, torch.Generator().manual_seed(seed), impact=0.6, distance=distance)


SURFACE_RAYS = {"slab": (SLAB, dict(impact=0.0, distance=(3.5, 4.5), cone_degrees=60.0)),  # crossings in [2.5, 5.5]
                "shell": (SHELL, dict(impact=1.1, distance=(3.5, 4.5)))}


def surface_rays(name, n=256, seed=0):
    field, kwargs = SURFACE_RAYS[name]
    return field, aimed_rays(n, torch.Generator().manual_seed(seed), **kwargs)


def test_stratified_opacity_of_a_blob_inside_the_range_converges_faster_than_any_power():
    # Expected: |opacity error| <= T(far) (exp(2 tau exp(-2 pi^2 r^2 / h^2)) - 1) (Poisson summation);
    # the bound is attained for some placements of the blob's centre in the grid, and at N = 16 the
    # error (exp(-28) relative) is at the level of the blob's tails beyond near and far (< 1e-7 density).
    rays = blob_rays(distance=(3.8, 4.2))
    truth = BLOB.truth(*rays, NEAR, FAR)
    tau = -torch.log1p(-truth["opacity"])
    ratios = []
    for n in (6, 8, 10):
        h = (FAR - NEAR) / n
        bound = (1 - truth["opacity"]) * torch.expm1(2 * tau * math.exp(-2 * math.pi**2 * BLOB.radius**2 / h**2))
        error = (render(BLOB, *rays, n, hierarchical=False)[0]["opacity"] - truth["opacity"]).abs()
        ratios.append((error / bound).max().item())
    assert max(ratios) <= 1.01 and min(ratios) > 0.5
    errors = convergence(BLOB, rays, [8, 16, 32], hierarchical=False, deterministic=True)
    assert errors["opacity"][1] < 1e-3 * errors["opacity"][0]  # a second-order rule would give 1/4
    assert errors["opacity"][2] < 1e-9
    ns = [16, 32, 64, 128, 256]
    assert 1.9 < observed_order(ns, convergence(BLOB, rays, ns, False, True)["depth"]) < 2.1  # depth: second order


@pytest.mark.parametrize("cut, distance, expected_order", [("near", (1.7, 2.3), 2), ("far", (5.7, 6.3), 1)])
def test_stratified_blob_cut_by_the_range_converges_at_the_predicted_order_and_constant(cut, distance, expected_order):
    rays = blob_rays(distance)
    truth = BLOB.truth(*rays, NEAR, FAR)
    ns = [32, 64, 128, 256, 512]
    errors = convergence(BLOB, rays, ns, hierarchical=False, deterministic=True)
    assert abs(observed_order(ns, errors["opacity"]) - expected_order) < 0.1
    assert abs(observed_order(ns, errors["depth"]) - expected_order) < 0.15
    # The leading term itself, ray by ray, at N = 512: (h^2/24) sigma'(near) T(far) or -(h/2) sigma(far) T(far).
    origins, directions = rays
    h = (FAR - NEAR) / ns[-1]
    rendered = render(BLOB, origins, directions, ns[-1], hierarchical=False)[0]["opacity"]
    end = NEAR if cut == "near" else FAR
    t = torch.tensor([end - 1e-3, end, end + 1e-3], dtype=torch.float64)  # sigma' by central difference
    sigma = BLOB(origins[:, None] + t[:, None] * directions[:, None], directions[:, None]).sigma
    if cut == "near":
        predicted = (h**2 / 24) * (sigma[:, 2] - sigma[:, 0]) / 2e-3 * (1 - truth["opacity"])
    else:
        predicted = -(h / 2) * sigma[:, 1] * (1 - truth["opacity"])
    torch.testing.assert_close(rendered - truth["opacity"], predicted, rtol=0.05, atol=0)


def test_stratified_jitter_on_a_smooth_blob_is_order_three_halves():
    torch.manual_seed(0)
    ns = [64, 128, 256, 512, 1024]  # below 64 the O(h^2) part of the error still shows (local orders near 2)
    errors = convergence(BLOB, blob_rays((3.8, 4.2), n=512), ns, hierarchical=False, deterministic=False)
    for quantity in ("opacity", "depth"):
        assert 1.3 < observed_order(ns, errors[quantity]) < 1.7, quantity


STRATIFIED_NS, HIERARCHICAL_NS = [64, 128, 256, 512, 1024, 2048], [128, 256, 512, 1024, 2048, 4096]


@pytest.fixture(scope="module")
def surface_convergence():
    """Deterministic (test-time) renders of the surface rays, shared by the tests below:
    {(name, hierarchical): (evaluations per ray [per N], {quantity: [error per N]})}."""
    results = {}
    for name in SURFACE_RAYS:
        field, rays = surface_rays(name)
        truth = field.truth(*rays, NEAR, FAR, WHITE)
        for hierarchical, ns in ((False, STRATIFIED_NS), (True, HIERARCHICAL_NS)):
            runs = [render(field, *rays, n, hierarchical) for n in ns]
            errors = [render_errors(out, truth) for out, _ in runs]
            results[name, hierarchical] = ([e for _, e in runs], {k: [e[k] for e in errors] for k in errors[0]})
    return results


@pytest.mark.parametrize("name", SURFACE_RAYS)
def test_deterministic_rendering_of_surfaces_is_first_order(name, surface_convergence):
    # Stratified from N = 64 (spacing 1/16, which resolves the 0.1 thick shell); hierarchical from 128
    # coarse samples (N = 512): with fewer the coarse pass misses parts of the shell, and the fine samples
    # that a face with little light left gets are too few for the asymptotic rate (local orders 0.6-0.9).
    for hierarchical, ns, first in ((False, STRATIFIED_NS, 0), (True, HIERARCHICAL_NS, 2)):
        _, errors = surface_convergence[name, hierarchical]
        for quantity in ("opacity", "depth", "rgb"):
            assert 0.8 < observed_order(ns[first:], errors[quantity][first:]) < 1.2, (hierarchical, quantity)


@pytest.mark.parametrize("name", SURFACE_RAYS)
def test_jittered_rendering_of_surfaces_is_first_order(name):
    torch.manual_seed(0)
    field, rays = surface_rays(name, n=128)
    # Jittered coarse samples leave gaps up to twice their spacing: hierarchical from 128 coarse samples.
    for hierarchical, ns in ((False, [64, 128, 256, 512, 1024]), (True, [512, 1024, 2048, 4096])):
        errors = convergence(field, rays, ns, hierarchical, deterministic=False)
        for quantity in ("opacity", "depth"):
            assert 0.8 < observed_order(ns, errors[quantity]) < 1.25, (hierarchical, quantity)


@pytest.mark.parametrize("name", SURFACE_RAYS)
def test_colour_error_of_one_colour_is_its_opacity_error_times_colour_minus_background(name):
    field, rays = surface_rays(name, n=64)
    truth = field.truth(*rays, NEAR, FAR, WHITE)
    out = render(field, *rays, 64, hierarchical=True)[0]
    gap = torch.tensor(field.colour, dtype=torch.float64) - torch.tensor(WHITE, dtype=torch.float64)
    torch.testing.assert_close(out["rgb"] - truth["rgb"], (out["opacity"] - truth["opacity"])[:, None] * gap)


def test_hierarchical_rendering_of_a_smooth_blob_is_first_order():
    # First order once the fine samples reach the blob's tails (N >~ 1000 here); the stratified midpoint
    # rule's super-algebraic opacity and second-order depth are lost to the uneven spacing.
    ns = [1024, 2048, 4096]
    errors = convergence(BLOB, blob_rays((3.8, 4.2), n=64), ns, hierarchical=True, deterministic=True)
    for quantity in ("opacity", "depth"):
        assert 0.85 < observed_order(ns, errors[quantity]) < 1.15, quantity
    stratified = convergence(BLOB, blob_rays((3.8, 4.2), n=64), [1024], hierarchical=False, deterministic=True)
    assert stratified["opacity"][0] < 1e-3 * errors["opacity"][0] and stratified["depth"][0] < errors["depth"][-1]


@pytest.mark.parametrize("name, quantity, target, saving", [
    ("slab", "depth", 2e-3, 1.5), ("shell", "depth", 2e-3, 4.0), ("shell", "opacity", 1e-3, 1.3)])
def test_hierarchical_sampling_reaches_an_accuracy_with_fewer_network_evaluations(name, quantity, target, saving,
                                                                                   surface_convergence):
    # The paper's claim, measured on surfaces with deterministic (test-time) sampling: network evaluations
    # per ray for a given mean error, stratified (N) against hierarchical (N / 4 coarse, then N / 4 + 3 N / 4
    # fine: 1.25 N). Not for the slab's opacity: its error comes from the back face, where little light is
    # left and hierarchical sampling puts few samples (see benchmarks/results/quadrature.md).
    needed = {}
    for hierarchical in (False, True):
        evaluations, errors = surface_convergence[name, hierarchical]
        needed[hierarchical] = cost_for_error(target, evaluations, errors[quantity])
        assert needed[hierarchical] is not None and needed[hierarchical] > evaluations[0], "target not bracketed"
    assert needed[True] * saving < needed[False]


def test_cost_for_error_interpolates_in_log_log_after_the_last_crossing():
    assert math.isclose(cost_for_error(1e-2, [10, 100], [1e-1, 1e-3]), math.sqrt(10 * 100))
    assert math.isclose(cost_for_error(1e-2, [10, 20, 40, 80], [1e-1, 1e-3, 1e-1, 1e-3]), math.sqrt(40 * 80))
    assert cost_for_error(1e-2, [10, 20], [1e-3, 1e-4]) == 10 and cost_for_error(1e-2, [10, 20], [1, 1e-1]) is None


def test_hierarchical_sampling_misses_a_shell_thinner_than_the_coarse_spacing():
    # 16 coarse samples are 0.25 apart; a shell 0.05 thick is seen by the coarse pass on some rays only,
    # and where the coarse pass misses a wall the fine samples go elsewhere: more fine samples do not help.
    field = Shell(thickness=0.05, density=20.0)
    rays = aimed_rays(256, torch.Generator().manual_seed(0), impact=1.05, distance=(3.5, 4.5))
    truth = field.truth(*rays, NEAR, FAR, WHITE)
    errors = [render_errors(render(field, *rays, 16 + n_fine, True, n_coarse=16)[0], truth)["opacity"]
              for n_fine in (128, 512, 2048)]
    assert errors[2] > 0.5 * errors[0] > 1e-2
    stratified = render_errors(render(field, *rays, 2080, hierarchical=False)[0], truth)["opacity"]
    assert stratified < 0.1 * errors[2]  # the same 2080 network evaluations per ray, evenly spread
