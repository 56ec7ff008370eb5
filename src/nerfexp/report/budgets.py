"""Variants compared at each budget: the test scores a run recorded part-way through its training
(``results.json``'s ``test_budgets``, ``nerfexp.rundir.records.BUDGET_FIELDS``), paired by seed with the
reference's at the same step, and at the same training time.

A *budget* is one scoring of a run's test views: after ``step`` optimizer steps, at ``train_time_s`` seconds of
its training clock. A run of an earlier nerfexp, without ``test_budgets``, has one: its end. At a *step* two
variants are compared where every one of their finished runs was scored there (``shared_steps``). At a *time*
each run's test score is interpolated linearly in training seconds between its budgets, never extrapolated
(``score_at_time``: None before its first budget and after its end), and two variants are compared at a time
only where every one of their runs has a score there (``time_window``: from the latest first budget to the
shortest run's total), so that no seed drops out of a pair for being slow. Times are compared only between
runs on one machine that had it to themselves (``nerfexp.report.shared_machines.timed_labels``); a variant with a
run that shared it is compared by step only (the report says why once: ``timing_caveats``).
"""

import bisect
import math
import statistics
from collections.abc import Hashable
from dataclasses import dataclass

from nerfexp.report.comparison import SEED, Difference, paired_difference, tiers
from nerfexp.report.runs import Budget, Run
from nerfexp.report.shared_machines import timed_labels
from nerfexp.report.variants import Variant
from nerfexp.rundir.records import is_scored

METRICS = ("psnr", "ssim")  # the test scores compared at each budget
CURVE_POINTS = 50  # matched times of a difference-against-time curve


def run_budgets(run: Run) -> list[Budget]:
    """A finished run's budgets in step order (``Run.budgets``: its ``test_budgets``, or an earlier nerfexp's run's
    end); none where it has none (or is not finished)."""
    return run.budgets


def budget_at(run: Run, step: int) -> Budget | None:
    """``run``'s budget at ``step``, or None (found by bisection: a run's budgets are in step order)."""
    budgets = run_budgets(run)
    i = bisect.bisect_left(budgets, step, key=lambda budget: budget.step)
    return budgets[i] if i < len(budgets) and budgets[i].step == step else None


def last_steps(runs: list[Run]) -> set[int]:
    """The steps the ``runs`` ended at (their last budgets')."""
    return {budgets[-1].step for run in runs if (budgets := run_budgets(run))}


def shared_steps(variants: list[Variant]) -> list[int]:
    """The steps at which every finished run of every one of ``variants`` was scored, increasing."""
    steps = [{budget.step for budget in run_budgets(run)} for variant in variants for run in variant.finished]
    return sorted(set.intersection(*steps)) if steps else []


def scores_at_step(variant: Variant, step: int, metric: str = "psnr") -> dict[Hashable, float]:
    """The test ``metric`` of each of ``variant``'s finished runs scored at ``step``, keyed by seed."""
    return {variant.seed_of(run): budget.score(metric) for run in variant.finished
            if (budget := budget_at(run, step)) is not None and is_scored(budget.score(metric))}


def step_differences(variant: Variant, reference: Variant, metric: str = "psnr") -> dict[int, Difference]:
    """``variant`` - ``reference`` in the test ``metric`` at each step both share (``shared_steps``), paired by
    seed; in step order."""
    return {step: paired_difference(scores_at_step(variant, step, metric), scores_at_step(reference, step, metric),
                                    variant.paired_by) for step in shared_steps([variant, reference])}


def score_at_time(budgets: list[Budget], time_s: float, metric: str = "psnr") -> float | None:
    """The test ``metric`` at training time ``time_s``, linear between the two budgets around it
    (v0 + (v1 - v0) (t - t0) / (t1 - t0)); None before the first budget, after the last, or where a score
    it needs is not one. Example: budgets (10 s, 20 dB), (30 s, 24 dB): at 15 s, 21 dB; at 5 s and 31 s, None."""
    if not budgets or not budgets[0].train_time_s <= time_s <= budgets[-1].train_time_s:
        return None
    i = bisect.bisect_left(budgets, time_s, key=lambda budget: budget.train_time_s)  # the first at time_s or after
    before, after = budgets[max(i - 1, 0)], budgets[i]
    t0, t1, v0, v1 = before.train_time_s, after.train_time_s, before.score(metric), after.score(metric)
    if not (is_scored(v0) and is_scored(v1)):
        return None
    return v1 if t1 == t0 else v0 + (v1 - v0) * (time_s - t0) / (t1 - t0)


def scores_at_time(variant: Variant, time_s: float, metric: str = "psnr") -> dict[Hashable, float]:
    """The test ``metric`` of each of ``variant``'s finished runs at training time ``time_s`` (``score_at_time``),
    keyed by seed; a run without one there is left out."""
    return {variant.seed_of(run): value for run in variant.finished
            if (value := score_at_time(run_budgets(run), time_s, metric)) is not None}


def time_window(variants: list[Variant]) -> tuple[float, float] | None:
    """The training times at which every finished run of ``variants`` has a test score: from the latest first
    budget to the shortest run's total; None where there are none."""
    budgets = [run_budgets(run) for variant in variants for run in variant.finished]
    if not budgets or not all(budgets):
        return None
    start, end = max(b[0].train_time_s for b in budgets), min(b[-1].train_time_s for b in budgets)
    return (start, end) if start <= end else None


def time_differences(variant: Variant, reference: Variant, times: list[float], metric: str = "psnr"
                     ) -> dict[float, Difference]:
    """``variant`` - ``reference`` in the test ``metric`` at each of ``times`` within the pair's ``time_window``,
    each run's score interpolated (``scores_at_time``), paired by seed."""
    window = time_window([variant, reference])
    if window is None:
        return {}
    return {t: paired_difference(scores_at_time(variant, t, metric), scores_at_time(reference, t, metric),
                                 variant.paired_by) for t in times if window[0] <= t <= window[1]}


def difference_curve(variant: Variant, reference: Variant, points: int = CURVE_POINTS
                     ) -> list[tuple[float, Difference]]:
    """``variant`` - ``reference`` in test PSNR at ``points`` times evenly spread over the pair's ``time_window``
    (one time where it is a single instant), for the difference-against-time plot."""
    window = time_window([variant, reference])
    if window is None:
        return []
    start, end = window
    times = [start + (end - start) * i / (points - 1) for i in range(points)] if end > start else [start]
    return list(time_differences(variant, reference, times).items())


def scoring_seconds(variants: list[Variant]) -> float | None:
    """The mean over the finished runs that recorded it of ``budget_scoring_s`` (the seconds scoring their
    mid-training budgets took, outside their training clock); None where none did."""
    seconds = [run.results["budget_scoring_s"] for v in variants for run in v.finished
               if run.results.get("budget_scoring_s") is not None]
    return statistics.fmean(seconds) if seconds else None


def budget_times(variant: Variant) -> list[float]:
    """The mean training time of ``variant``'s finished runs at each step they all share (``shared_steps``)."""
    return [statistics.fmean(budget_at(run, step).train_time_s for run in variant.finished)
            for step in shared_steps([variant])]


def budget_points(variant: Variant) -> list[tuple[int, float, float]]:
    """(step, mean training time, mean test PSNR) of ``variant``'s finished runs at each step they all share and
    all scored, for the Pareto plot."""
    points = []
    for step, time_s in zip(shared_steps([variant]), budget_times(variant)):
        scores = scores_at_step(variant, step)
        if scores and len(scores) == len(variant.finished):
            points.append((step, time_s, statistics.fmean(scores.values())))
    return points


def equal_times(variants: list[Variant]) -> tuple[Variant | None, list[float]]:
    """The times the equal-time tables rank at: of the fastest timed variant (the lowest mean training time of
    those with finished runs, ``timed_labels``), the mean time of each of its budgets, each brought into the times
    at which every one of its runs has a score (``time_window``: a mean first budget before a slower seed's first,
    or a mean total past a faster seed's end, would leave some of its own runs out), its total the last, each
    time once; (None, []) where no variant is timed."""
    timed = timed_labels(variants)
    candidates = [v for v in variants if v.label in timed and math.isfinite(v.mean("train_time_s"))]
    if not candidates:
        return None, []
    fastest = min(candidates, key=lambda v: v.mean("train_time_s"))
    window = time_window([fastest])
    if window is None:
        return fastest, []
    return fastest, list(dict.fromkeys(min(max(t, window[0]), window[1]) for t in budget_times(fastest)))


@dataclass(frozen=True)
class EqualTime:
    """Variants at training time ``time_s``: ``ranked`` (label, mean interpolated test PSNR over its runs that
    cover the time, their number) best first, cut into ``groups`` the seeds do not resolve (``tiers``), and
    ``uncovered`` (label, why it has no score there)."""

    time_s: float
    ranked: list[tuple[str, float, int]]
    groups: list[list[str]]
    uncovered: list[tuple[str, str]]


def seconds_text(time_s: float) -> str:
    """A training time as the report writes it: whole seconds from 10 s on ("1,234 s"), else 3 significant
    digits ("0.646 s")."""
    return f"{time_s:,.0f} s" if time_s >= 10 else f"{time_s:.3g} s"


def uncovered_reason(variant: Variant, time_s: float) -> str:
    """Why no run of ``variant`` has a test score at ``time_s``: each tested first after it, or ended before it."""
    budgets = [b for run in variant.finished if (b := run_budgets(run))]
    if budgets and all(b[0].train_time_s > time_s for b in budgets):
        first = min(b[0].train_time_s for b in budgets)
        return f"first test after {seconds_text(time_s)} (at {seconds_text(first)})"
    if budgets and all(b[-1].train_time_s < time_s for b in budgets):
        return f"training ended before {seconds_text(time_s)}"
    return f"no run has a test score at {seconds_text(time_s)}"


def equal_time(variants: list[Variant], time_s: float) -> EqualTime:
    """The timed ``variants`` (``timed_labels``) ranked by mean test PSNR at training time ``time_s``, each over its
    runs that have a score there (``scores_at_time``), grouped where their difference there, paired by seed, is not
    resolved (``nerfexp.report.comparison.tiers``); the rest named with why (``uncovered_reason``)."""
    timed = timed_labels(variants)
    timed_variants = [v for v in variants if v.label in timed]
    scores = {v.label: scores_at_time(v, time_s) for v in timed_variants}
    ranked = sorted(((label, statistics.fmean(s.values()), len(s)) for label, s in scores.items() if s),
                    key=lambda item: -item[1])
    unit = timed_variants[0].paired_by if timed_variants else SEED
    groups = tiers([label for label, _, _ in ranked], lambda a, b: paired_difference(scores[a], scores[b], unit))
    uncovered = [(v.label, uncovered_reason(v, time_s)) for v in timed_variants if not scores[v.label]]
    return EqualTime(time_s, ranked, groups, uncovered)


def steps_text(steps: list[int]) -> str:
    """"500", "500 and 1,000", "250, 500 and 1,000"."""
    written = [f"{step:,}" for step in steps]
    return written[0] if len(written) == 1 else ", ".join(written[:-1]) + " and " + written[-1]


def budget_words(differences: dict[int, Difference], unit: str = " dB") -> str:
    """What a verdict needs said of its budgets, from ``differences`` (step -> Difference, in step order;
    steps without a pair left out), or "" where the verdict is the same at every budget and not still moving:
    "depends on the budget: worse at 500 steps, not resolved at 1,500" where the verdicts differ (consecutive
    equal ones merged), and "still moving: +0.52 dB from 750 to 1,500 steps, more than the interval's
    half-width (0.31)" where the mean moved between the last two budgets by more than the last interval's
    half-width; both, joined by "; ", where both hold."""
    steps = [step for step, d in differences.items() if d.n > 0]
    words = []
    runs: list[tuple[str, list[int]]] = []  # (verdict, its consecutive steps)
    for step in steps:
        verdict = differences[step].verdict
        if runs and runs[-1][0] == verdict:
            runs[-1][1].append(step)
        else:
            runs.append((verdict, [step]))
    if len(runs) > 1:
        words.append("depends on the budget: " + ", ".join(
            f"{verdict} at {steps_text(group)}" + (" steps" if i == 0 else "") for i, (verdict, group) in
            enumerate(runs)))
    if len(steps) > 1 and (last := differences[steps[-1]]).interval is not None:
        half = (last.interval[1] - last.interval[0]) / 2
        moved = last.mean - differences[steps[-2]].mean
        if abs(moved) > half:
            words.append(f"still moving: {moved:+.2f}{unit} from {steps[-2]:,} to {steps[-1]:,} steps, more than "
                         f"the interval's half-width ({half:.2f})")
    return "; ".join(words)
