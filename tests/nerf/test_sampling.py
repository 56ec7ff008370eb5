import math

import pytest
import torch

from nerfexp.nerf.sampling import dilate_weights, intervals, sample_pdf, stratified_samples


def test_stratified_one_sample_per_bin(device):
    near, far = torch.full((1000,), 2.0, device=device), torch.full((1000,), 6.0, device=device)
    t = stratified_samples(near, far, 8, deterministic=False, generator=torch.Generator(device).manual_seed(0))
    edges = torch.linspace(2, 6, 9, device=device)
    assert ((t >= edges[:-1]) & (t <= edges[1:])).all()
    # jitter covers each bin: the mean position within a bin is about its middle
    torch.testing.assert_close(t.mean(0), 0.5 * (edges[:-1] + edges[1:]), atol=0.05, rtol=0)
    mids = stratified_samples(near[:1], far[:1], 8, deterministic=True)
    torch.testing.assert_close(mids[0], 0.5 * (edges[:-1] + edges[1:]))


def test_intervals_start_at_each_sample_and_the_last_ends_at_far():
    t = torch.tensor([[2.5, 3.0, 5.0]])
    starts, ends = intervals(t, torch.tensor([6.0]))
    assert torch.equal(starts, t) and torch.equal(ends, torch.tensor([[3.0, 5.0, 6.0]]))


def _chi_square_pvalue_upper(stat: float, dof: int) -> float:
    """P(X > stat) for X ~ chi^2(dof), by the Wilson-Hilferty normal approximation."""
    z = ((stat / dof) ** (1 / 3) - (1 - 2 / (9 * dof))) / math.sqrt(2 / (9 * dof))
    return 0.5 * math.erfc(z / math.sqrt(2))


def test_sample_pdf_recovers_piecewise_constant_density(device):
    # Goodness of fit: the histogram of samples over the bins follows the weights (chi-square test),
    # and within a bin the samples are uniform (a second chi-square on half-bins).
    bins = torch.tensor([0.0, 1.0, 1.5, 4.0, 4.2, 6.0], dtype=torch.float64)
    weights = torch.tensor([0.1, 0.0, 0.5, 0.3, 0.1], dtype=torch.float64)
    n = 200_000
    samples = sample_pdf(bins.to(device), weights.to(device), n, deterministic=False,
                         generator=torch.Generator(device).manual_seed(1)).cpu()
    assert samples.shape == (n,)
    assert (samples[1:] >= samples[:-1]).all()  # sorted
    half_edges = torch.stack([bins[:-1], 0.5 * (bins[:-1] + bins[1:])], 1).flatten()
    half_edges = torch.cat([half_edges, bins[-1:]])
    counts = torch.histogram(samples, half_edges).hist
    expected = (weights / weights.sum()).repeat_interleave(2) / 2 * n
    assert counts[2:4].sum() == 0  # nothing lands in the empty bin
    mask = expected > 0
    stat = (((counts - expected) ** 2)[mask] / expected[mask]).sum().item()
    assert _chi_square_pvalue_upper(stat, int(mask.sum()) - 1) > 1e-3, stat


def test_sample_pdf_is_stratified_each_bin_gets_its_share_on_every_ray():
    # One u in each n-th of the CDF: a bin of mass w gets n w samples, less than 2 off (its two end
    # strata may or may not land in it), on every ray; n sorted uniform u would give n w +- sqrt(n w),
    # +- 5.7 for the heaviest bin here, far outside.
    bins = torch.tensor([2.0, 2.5, 3.0, 4.0, 4.1, 6.0], dtype=torch.float64).expand(5000, 6)
    weights = torch.tensor([0.05, 0.5, 0.0, 0.3, 0.15], dtype=torch.float64).expand(5000, 5)
    n = 64
    samples = sample_pdf(bins, weights, n, deterministic=False, generator=torch.Generator().manual_seed(2))
    bin_of = torch.searchsorted(bins[0], samples, right=True) - 1  # [rays, n]
    counts = torch.nn.functional.one_hot(bin_of, 5).sum(1).double()  # [rays, bins]
    assert (counts - n * weights).abs().max() < 2
    assert counts[:, 2].sum() == 0
    # and a sample's position within its stratum is uniform: the mean sample is the mean of the PDF
    torch.testing.assert_close(samples.mean(), (weights[0] * 0.5 * (bins[0, 1:] + bins[0, :-1])).sum(),
                               atol=2e-3, rtol=0)


def test_sample_pdf_u_rounding_to_one_stays_in_mass(monkeypatch):
    # (n - 1 + xi) / n rounds to 1 in float32 for xi close to 1; such a u must still land in the bin
    # with mass, not in the empty bins after it.
    almost_one = 1 - 2.0**-24  # the largest float32 below 1
    assert (31 + torch.tensor(almost_one)) / 32 == 1  # the rounding guarded against
    monkeypatch.setattr(torch, "rand", lambda shape, **kw: torch.full(shape, almost_one, dtype=kw.get("dtype")))
    samples = sample_pdf(torch.tensor([[0.0, 1.0, 2.0, 3.0]]), torch.tensor([[1.0, 0.0, 0.0]]), 32,
                         deterministic=False)
    assert samples.max() <= 1.0


def test_sample_pdf_deterministic_quantiles_by_hand():
    # Two bins [0, 1], [1, 3] with masses 1 : 3. u = 1/8, 3/8, 5/8, 7/8.
    # CDF: 0 at 0, 1/4 at 1, 1 at 3. u = 1/8 -> 0.5; 3/8 -> 1 + 2 (1/8)/(3/4) = 4/3; 5/8 -> 2; 7/8 -> 8/3.
    out = sample_pdf(torch.tensor([0.0, 1.0, 3.0]), torch.tensor([1.0, 3.0]), 4, deterministic=True)
    torch.testing.assert_close(out, torch.tensor([0.5, 4 / 3, 2.0, 8 / 3]))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_sample_pdf_all_zero_weights_is_uniform(dtype):
    bins = torch.linspace(2, 6, 5, dtype=dtype).expand(3, 5)
    out = sample_pdf(bins, torch.zeros(3, 4, dtype=dtype), 4, deterministic=True)
    torch.testing.assert_close(out, torch.tensor([2.5, 3.5, 4.5, 5.5], dtype=dtype).expand(3, 4))


def test_sample_pdf_all_mass_in_one_bin_and_single_bin():
    out = sample_pdf(torch.tensor([0.0, 1.0, 2.0, 3.0]), torch.tensor([0.0, 2.0, 0.0]), 64,
                     deterministic=False, generator=torch.Generator().manual_seed(0))
    assert ((out >= 1.0) & (out <= 2.0)).all()
    single = sample_pdf(torch.tensor([[2.0, 6.0]]), torch.tensor([[0.7]]), 5, deterministic=True)
    torch.testing.assert_close(single, torch.tensor([[2.4, 3.2, 4.0, 4.8, 5.6]]))


def test_sample_pdf_detaches_positions():
    weights = torch.rand(4, 8, requires_grad=True)
    bins = torch.linspace(0, 1, 9).expand(4, 9).clone().requires_grad_()
    out = sample_pdf(bins, weights, 16, deterministic=False)
    assert not out.requires_grad and torch.isfinite(out).all()


def test_dilate_weights_by_hand():
    w = torch.tensor([[0.0, 0.0, 0.3, 0.1, 0.0, 0.0, 0.2]])
    assert torch.equal(dilate_weights(w), torch.tensor([[0.0, 0.3, 0.3, 0.3, 0.1, 0.2, 0.2]]))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_sample_pdf_zero_width_bins_hold_their_samples_at_the_edge(dtype):
    # bins [0, 1], [1, 1] (zero width, half the mass), [1, 3]: half the quantiles land exactly at 1.
    out = sample_pdf(torch.tensor([0.0, 1.0, 1.0, 3.0], dtype=dtype), torch.tensor([1.0, 2.0, 1.0], dtype=dtype), 8,
                     deterministic=True)
    # CDF: 0, 1/4, 3/4, 1. u = (k + 1/2)/8: 1/16 -> 0.25, 3/16 -> 0.75, 5/16..11/16 -> 1, 13/16 -> 1.5, 15/16 -> 2.5
    expected = torch.tensor([0.25, 0.75, 1.0, 1.0, 1.0, 1.0, 1.5, 2.5], dtype=dtype)
    torch.testing.assert_close(out, expected)


def test_sample_pdf_nan_weights_are_not_hidden():
    # a NaN weight means the coarse pass failed: the samples say so instead of silently going uniform
    out = sample_pdf(torch.tensor([0.0, 1.0, 2.0]), torch.tensor([float("nan"), 1.0]), 4, deterministic=True)
    assert torch.isnan(out).any()


def test_sample_pdf_deterministic_is_reproducible_and_random_follows_the_generator():
    bins, weights = torch.linspace(0, 1, 9).expand(2, 9), torch.rand(2, 8)
    assert torch.equal(sample_pdf(bins, weights, 16, True), sample_pdf(bins, weights, 16, True))
    a = sample_pdf(bins, weights, 16, False, generator=torch.Generator().manual_seed(3))
    b = sample_pdf(bins, weights, 16, False, generator=torch.Generator().manual_seed(3))
    assert torch.equal(a, b)


# ---- properties (hypothesis) -----------------------------------------------------------------------

from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@st.composite
def pdfs(draw):
    """Bins [S+1] from a start in [0, 10] and widths from 0 (zero-width bins) to 1e3; masses [S] with
    zeros, tiny and large values; S from 1 (a single bin)."""
    S = draw(st.integers(1, 20))
    widths = draw(st.lists(st.one_of(st.just(0.0), st.floats(1e-6, 1e3)), min_size=S, max_size=S))
    masses = draw(st.lists(st.one_of(st.just(0.0), st.floats(1e-30, 1.0), st.floats(1.0, 1e6)), min_size=S,
                           max_size=S))
    start = draw(st.floats(0.0, 10.0))
    edges = [start]
    for w in widths:
        edges.append(edges[-1] + w)
    return edges, masses


def cdf_at(x: torch.Tensor, bins: torch.Tensor, masses: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """float64 CDF of the piecewise-constant density just below and just above each x, by a direct sum
    over bins (independent of sample_pdf): F(x-) and F(x+) differ only at zero-width bins holding mass."""
    p = masses / masses.sum() if masses.sum() > 0 else torch.full_like(masses, 1 / len(masses))
    lo, hi = bins[:-1], bins[1:]
    width = hi - lo
    inside = torch.where(width > 0, ((x[:, None] - lo) / torch.where(width > 0, width, 1)).clamp(0, 1), 0)
    below = (p * torch.where(width > 0, inside, (x[:, None] > lo).double())).sum(-1)
    above = (p * torch.where(width > 0, inside, (x[:, None] >= lo).double())).sum(-1)
    return below, above


@settings(max_examples=300, deadline=None)
@given(pdfs(), st.integers(1, 64), st.sampled_from([torch.float32, torch.float64]), st.booleans())
def test_sample_pdf_properties(pdf, n, dtype, deterministic):
    edges, masses = pdf
    bins, weights = torch.tensor(edges, dtype=dtype), torch.tensor(masses, dtype=dtype)
    out = sample_pdf(bins, weights, n, deterministic, generator=torch.Generator().manual_seed(0))
    assert out.shape == (n,) and out.dtype == dtype and torch.isfinite(out).all()
    assert (out[1:] >= out[:-1]).all()  # sorted
    assert (out >= bins[0]).all() and (out <= bins[-1]).all()
    # every sample lies in a bin that holds mass (any bin when there is none)
    held = weights > 0 if weights.sum() > 0 else torch.ones_like(weights, dtype=torch.bool)
    in_bin = (out[:, None] >= bins[:-1]) & (out[:, None] <= bins[1:])
    assert (in_bin & held).any(-1).all()
    if deterministic:  # the k-th sample is the (k + 1/2)/n quantile, to float precision in the CDF
        u = (torch.arange(n, dtype=torch.float64) + 0.5) / n
        below, above = cdf_at(out.double(), bins.double(), weights.double())
        # tolerance: the CDF's own rounding, plus the rounding of the sample's position (half an ulp of
        # |x|) times the steepest density
        p = weights.double() / weights.double().sum() if weights.sum() > 0 else torch.ones(len(weights)) / len(weights)
        widths = (bins[1:] - bins[:-1]).double()
        steepest = (p / widths)[widths > 0].max() if (widths > 0).any() else torch.tensor(0.0)
        eps = torch.finfo(dtype).eps
        tol = 64 * eps + 2 * eps * out.double().abs() * steepest
        assert ((below - tol <= u) & (u <= above + tol)).all()
