"""Paired comparisons over seeds: what a sweep's few seeds can and cannot tell apart.

Two variants' runs are paired by seed (the same seed: the same data order and, where the networks have
the same shapes, the same initial weights), and the mean of the per-seed differences gets a two-sided
95% confidence interval from Student's t with n - 1 degrees of freedom. A difference is resolved when
its interval excludes zero; one pair gives no interval. The intervals are per comparison, not corrected
for making many: among pairs with no real difference, about 1 in 20 is resolved by chance.
"""

import functools
import math
import statistics
from collections.abc import Callable, Hashable, Mapping, Sequence
from dataclasses import dataclass

from scipy.stats import t as student_t

LEVEL = 0.95  # the confidence level of every interval


SEED, PAIR = "seed", "pair"  # what a pair of runs is matched on, as the report counts them (``Variant.paired_by``)


def seeds(n: int, unit: str = SEED) -> str:
    """"1 seed", "3 seeds"; "4 pairs" (``unit``)."""
    return f"{n} {unit}{'' if n == 1 else 's'}"


@functools.cache
def t_quantile(probability: float, degrees: int) -> float:
    """Student's t quantile ``t_{probability, degrees}``, kept once asked: a report asks the same few (one per
    number of seeds) at every budget of every pair, and scipy takes longer over each than the rest of the pair."""
    return float(student_t.ppf(probability, degrees))


def t_interval(values: Sequence[float], level: float = LEVEL) -> tuple[float, float] | None:
    """The two-sided ``level`` confidence interval (low, high) of the mean of ``values`` from Student's t:
    mean -/+ t_{(1 + level) / 2, n - 1} * s / sqrt(n), s the sample standard deviation; None for n < 2."""
    n = len(values)
    if n < 2:
        return None
    mean = statistics.fmean(values)
    half = t_quantile((1 + level) / 2, n - 1) * statistics.stdev(values) / math.sqrt(n)
    return mean - half, mean + half


@dataclass(frozen=True)
class Difference:
    """The mean of paired differences a - b over ``n`` pairs and its 95% interval (None for n < 2); ``unit``: what
    the pairs are counted as (``SEED``; ``PAIR`` where runs are matched on more than their seed, a seed on a scene)."""

    mean: float
    n: int
    interval: tuple[float, float] | None
    unit: str = SEED

    @property
    def verdict(self) -> str:
        """better (the interval above zero), worse (below), or not resolved."""
        if self.interval is not None and self.interval[0] > 0:
            return "better"
        if self.interval is not None and self.interval[1] < 0:
            return "worse"
        return "not resolved"

    @property
    def resolved(self) -> bool:
        return self.verdict != "not resolved"

    def describe(self, digits: int) -> str:
        """E.g. ``+0.08 [-0.31, +0.47]``, or ``1 seed: no interval``, or ``no seeds in common``."""
        if self.n == 0:
            return f"no {self.unit}s in common"
        if self.interval is None:
            return f"{seeds(self.n, self.unit)}: no interval"
        low, high = self.interval
        return f"{self.mean:+.{digits}f} [{low:+.{digits}f}, {high:+.{digits}f}]"

    def verdict_text(self) -> str:
        """The verdict, with the number of seeds (or pairs) where it is not resolved."""
        if self.resolved:
            return self.verdict
        return f"not resolved with {seeds(self.n, self.unit)}"


def paired_difference(a: Mapping[Hashable, float], b: Mapping[Hashable, float], unit: str = SEED) -> Difference:
    """a - b over the seeds (keys) both have: their mean and its t-interval, counted in ``unit``."""
    differences = [a[seed] - b[seed] for seed in a if seed in b]
    mean = statistics.fmean(differences) if differences else math.nan
    return Difference(mean, len(differences), t_interval(differences), unit)


def tiers(ranked: Sequence[str], difference: Callable[[str, str], Difference]) -> list[list[str]]:
    """``ranked`` (best first) cut into groups: a group starts with its best and takes each next item
    whose difference to that best (``difference(best, item)``) is not resolved; the first item resolved
    below the group's best starts the next group."""
    groups: list[list[str]] = []
    for item in ranked:
        if groups and not difference(groups[-1][0], item).resolved:
            groups[-1].append(item)
        else:
            groups.append([item])
    return groups


@dataclass(frozen=True)
class OrderComparison:
    """Pairs (higher, lower) of an expected order, each as measured: ``agree`` (resolved the same way),
    ``reversed`` (resolved the other way), ``unresolved``."""

    agree: list[tuple[str, str]]
    reversed: list[tuple[str, str]]
    unresolved: list[tuple[str, str]]


def compare_order(expected: Sequence[str], difference: Callable[[str, str], Difference]) -> OrderComparison:
    """Every pair of ``expected`` (best first) against the measured ``difference(higher, lower)``."""
    agree, reversed_, unresolved = [], [], []
    for i, higher in enumerate(expected):
        for lower in expected[i + 1:]:
            verdict = difference(higher, lower).verdict
            {"better": agree, "worse": reversed_}.get(verdict, unresolved).append((higher, lower))
    return OrderComparison(agree, reversed_, unresolved)
