"""Paired comparisons over seeds, against values worked by hand (t quantiles from a printed t table)."""

import math

import pytest

from nerfexp.report.comparison import Difference, compare_order, paired_difference, t_interval, tiers

T_975 = {1: 12.7062, 2: 4.3027, 4: 2.7764}  # Student's t, two-sided 95%, by degrees of freedom (a t table)


def test_a_t_interval_from_known_numbers():
    # 1..5: mean 3, s = sqrt(10 / 4), s / sqrt(5) = sqrt(0.5); 4 degrees of freedom
    low, high = t_interval([1.0, 2.0, 3.0, 4.0, 5.0])
    half = T_975[4] * math.sqrt(0.5)
    assert (low, high) == pytest.approx((3 - half, 3 + half), abs=1e-4)
    # two values, 0 and 2: mean 1, s / sqrt(2) = 1; 1 degree of freedom: a wide interval
    assert t_interval([0.0, 2.0]) == pytest.approx((1 - T_975[1], 1 + T_975[1]), abs=1e-4)
    assert t_interval([5.0]) is None and t_interval([]) is None


def test_a_paired_difference_uses_only_the_seeds_both_have_and_an_unresolved_tie_says_so():
    variant = {0: 28.1, 1: 28.3, 2: 27.9, 3: 40.0}  # seed 3 has no partner: left out
    reference = {0: 28.0, 1: 28.0, 2: 28.0}
    difference = paired_difference(variant, reference)
    # differences 0.1, 0.3, -0.1: mean 0.1, s = 0.2, s / sqrt(3); 2 degrees of freedom
    half = T_975[2] * 0.2 / math.sqrt(3)
    assert difference.n == 3 and difference.mean == pytest.approx(0.1, abs=1e-12)
    assert difference.interval == pytest.approx((0.1 - half, 0.1 + half), abs=1e-4)
    assert difference.verdict == "not resolved" and not difference.resolved
    assert difference.verdict_text() == "not resolved with 3 seeds"
    assert difference.describe(2) == "+0.10 [-0.40, +0.60]"


def test_a_resolved_reversal_of_an_expected_order_is_named():
    scores = {"complete": {0: 28.0, 1: 28.0, 2: 28.0}, "no_posenc": {0: 29.0, 1: 29.1, 2: 28.9},
              "no_view_dependence": {0: 27.0, 1: 27.5, 2: 26.5}}

    def difference(a, b):
        return paired_difference(scores[a], scores[b])

    # complete - no_posenc: -1.0, -1.1, -0.9: mean -1, s = 0.1; the interval lies below zero
    reversal = difference("complete", "no_posenc")
    half = T_975[2] * 0.1 / math.sqrt(3)
    assert reversal.interval == pytest.approx((-1 - half, -1 + half), abs=1e-4) and reversal.verdict == "worse"
    order = compare_order(["complete", "no_posenc", "no_view_dependence"], difference)
    assert order.reversed == [("complete", "no_posenc")]
    # complete - no VD: 1.0, 0.5, 1.5 (s = 0.5: the interval is 1 -/+ 1.24, not resolved); no PE - no VD: 2.0,
    # 1.6, 2.4 (s = 0.4: 2 -/+ 0.99, resolved)
    assert order.unresolved == [("complete", "no_view_dependence")]
    assert order.agree == [("no_posenc", "no_view_dependence")]


def test_one_seed_gives_no_interval_and_no_verdict():
    difference = paired_difference({0: 30.0}, {0: 20.0})
    assert (difference.mean, difference.n, difference.interval) == (10.0, 1, None)
    assert difference.describe(2) == "1 seed: no interval" and difference.verdict_text() == "not resolved with 1 seed"
    assert paired_difference({0: 1.0}, {1: 1.0}).describe(2) == "no seeds in common"


def test_tiers_start_at_the_first_variant_resolved_below_the_tiers_best():
    resolved = {("a", "c"), ("a", "d"), ("c", "d")}

    def difference(best, item):  # resolved pairs: a clear gap; the rest: an interval across zero
        return Difference(1.0, 3, (0.5, 1.5)) if (best, item) in resolved else Difference(0.1, 3, (-0.5, 0.7))

    # b is not resolved from a; c is; d is resolved from c, the best of c's tier
    assert tiers(["a", "b", "c", "d"], difference) == [["a", "b"], ["c"], ["d"]]
    assert tiers([], difference) == []
