import math

import pytest
import torch

from nerfexp.sampling import dilate_weights, intervals, sample_pdf, stratified_samples


def test_stratified_one_sample_per_bin():
    near, far = torch.full((1000,), 2.0), torch.full((1000,), 6.0)
    t = stratified_samples(near, far, 8, deterministic=False, generator=torch.Generator().manual_seed(0))
    edges = torch.linspace(2, 6, 9)
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


def test_sample_pdf_recovers_piecewise_constant_density():
    # Goodness of fit: the histogram of samples over the bins follows the weights (chi-square test),
    # and within a bin the samples are uniform (a second chi-square on half-bins).
    bins = torch.tensor([0.0, 1.0, 1.5, 4.0, 4.2, 6.0], dtype=torch.float64)
    weights = torch.tensor([0.1, 0.0, 0.5, 0.3, 0.1], dtype=torch.float64)
    n = 200_000
    samples = sample_pdf(bins, weights, n, deterministic=False, generator=torch.Generator().manual_seed(1))
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
