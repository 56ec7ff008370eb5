"""The report's sections per budget (``nerfexp.report.budgets``): report.md's "Per budget" (each variant against the
reference at each shared step and matched training time) and "At equal training time" (the variants ranked at a
few training times), and ``report_budgets.csv``, the same differences one per line."""

import csv
import io
import math
from collections.abc import Callable

from nerfexp.report.budgets import (
    METRICS,
    by_step_only_line,
    equal_time,
    equal_times,
    last_steps,
    scoring_seconds,
    seconds_text,
    step_differences,
    time_differences,
    time_window,
    timed,
)
from nerfexp.report.comparison import Difference
from nerfexp.report.runs import Run
from nerfexp.report.variants import Variant

BUDGET_COLUMNS = ("variant", "reference", "metric", "kind", "budget", "n", "diff", "low", "high", "verdict")


def compared(variants: list[Variant], reference: Variant | None) -> list[Variant]:
    """The variants compared with ``reference``: the others with finished runs (none without a reference)."""
    if reference is None or not reference.finished:
        return []
    return [v for v in variants if v is not reference and v.finished]


def pair_times(variant: Variant, reference: Variant, times: list[float]) -> list[float]:
    """The matched times of ``variant`` and ``reference``: those of ``times`` in the pair's ``time_window`` and its
    end (the shortest of their runs' totals), increasing; none where their times may not be compared (``timed``)
    or no time has a score of every run."""
    window = time_window([variant, reference])
    if window is None or not (timed(variant) and timed(reference)):
        return []
    return sorted({t for t in times if window[0] <= t <= window[1]} | {window[1]})


def budget_rows(variants: list[Variant], reference: Variant | None) -> list[dict]:
    """report_budgets.csv's rows (``BUDGET_COLUMNS``): each compared variant - ``reference`` in each test score of
    ``METRICS``, at each shared step (kind step, budget: the step) and each matched time (kind time, budget: the
    seconds, ``equal_times``), with its number of seed pairs, 95% interval (NaN for fewer than two) and verdict."""
    times = equal_times(variants)[1]
    rows = []
    for variant in compared(variants, reference):
        for metric in METRICS:
            by_kind = (("step", step_differences(variant, reference, metric)),
                       ("time", time_differences(variant, reference, pair_times(variant, reference, times), metric)))
            for kind, differences in by_kind:
                for budget, d in differences.items():
                    low, high = d.interval or (math.nan, math.nan)
                    rows.append({"variant": variant.label, "reference": reference.label, "metric": metric,
                                 "kind": kind, "budget": budget, "n": d.n, "diff": d.mean, "low": low, "high": high,
                                 "verdict": d.verdict_text() if d.n else ""})
    return rows


def budgets_csv_text(rows: list[dict], safe: Callable[[object], object]) -> str:
    """report_budgets.csv from ``budget_rows``, each cell through ``safe`` (report.csv's spreadsheet guard,
    ``nerfexp.report.tables.csv_cell``)."""
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=BUDGET_COLUMNS, lineterminator="\n", quoting=csv.QUOTE_NONNUMERIC)
    writer.writeheader()
    writer.writerows({column: safe(row[column]) for column in BUDGET_COLUMNS} for row in rows)
    return out.getvalue()


def per_budget_text(variants: list[Variant], reference: Variant | None, words: dict[str, str]) -> list[str]:
    """report.md's "Per budget" section: one row per compared variant, a column per step any pair shares and per
    matched time (``equal_times``), each cell the PSNR difference to ``reference`` with its 95% interval, and the
    variant's budget ``words`` (label -> ``budget_words``)."""
    lines = ["## Per budget", ""]
    variants_compared = compared(variants, reference)
    if not variants_compared:
        return lines + ["No per-budget differences: they need a reference variant with finished runs and another "
                        "variant to compare with it."]
    fastest, times = equal_times(variants)
    steps = {v.label: step_differences(v, reference) for v in variants_compared}
    at_times = {v.label: time_differences(v, reference, pair_times(v, reference, times)) for v in variants_compared}
    columns = sorted({step for differences in steps.values() for step in differences})
    ends = {v.label: window[1] if (window := time_window([v, reference])) else None for v in variants_compared}
    lines += [f"Test PSNR - reference (`{reference.label}`), dB, paired by seed with its 95% interval: at each "
              "step where every run of both was scored, then at training times (the fastest timed variant's "
              "budgets' mean times, its total the last), each run's test PSNR interpolated linearly between its "
              "budgets, where every run of both has one (from the latest first test to the shortest run's total; "
              "never extrapolated), and at the shortest of the pair's runs' total training time. – : not shared. "
              "Budget verdict: where the verdict depends on the budget or is still moving between the last two "
              "steps."
              + ("" if (scoring := scoring_seconds(variants)) is None else
                 f" Scoring the budgets before the end took {seconds_text(scoring)} a run on average, outside "
                 "the training times."), ""]
    if (line := by_step_only_line(variants, reference)) is not None:
        lines += [line, ""]
    if fastest is None:
        lines += ["No comparison by training time: every variant has runs that shared their machine.", ""]
    header = ["variant", *(f"at {step:,} steps" for step in columns), *(f"at {seconds_text(t)}" for t in times),
              "at the pair's shortest run's total", "budget verdict"]
    lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for variant in variants_compared:
        cells = [variant.label, *(cell(steps[variant.label].get(step)) for step in columns),
                 *(cell(at_times[variant.label].get(t)) for t in times), end_cell(at_times[variant.label],
                                                                                   ends[variant.label]),
                 words.get(variant.label) or ("steady" if len(steps[variant.label]) > 1 else "–")]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def cell(difference: Difference | None) -> str:
    return "–" if difference is None else difference.describe(2)


def end_cell(differences: dict[float, Difference], end: float | None) -> str:
    """The difference at the pair's shortest run's total ``end``, with that time."""
    return "–" if end not in differences else f"{differences[end].describe(2)} at {seconds_text(end)}"


def equal_time_text(variants: list[Variant]) -> list[str]:
    """report.md's "At equal training time" section: at each of ``equal_times``, the timed variants ranked by mean
    test PSNR, those the seeds do not resolve on one line (``equal_time``), and those with no score there."""
    lines = ["## At equal training time", ""]
    fastest, times = equal_times(variants)
    if fastest is None:
        return lines + ["No ranking at equal training time: no variant has finished runs that had their machine "
                        "to themselves."]
    lines += [f"What is best for a given time on these machines: at the fastest variant's (`{fastest.label}`) total "
              "training time and at its budgets' times, each variant's test PSNR interpolated linearly between its "
              "runs' budgets (never extrapolated), the mean over its runs that have one; variants on one line are "
              "not resolved from the first of the line (paired by seed, 95% interval).", ""]
    if (line := by_step_only_line(variants, None)) is not None:
        lines += [line, ""]
    if not times:
        return lines + ["No time to rank at: the fastest variant's runs share no test step."]
    for time_s in times:
        table = equal_time(variants, time_s)
        means = {label: (mean, n) for label, mean, n in table.ranked}
        lines += [f"**At {seconds_text(time_s)}, ranked:**", ""]
        lines += [f"{i}. " + ", ".join(f"{label} ({means[label][0]:.2f} dB, {means[label][1]} "
                                        f"run{'' if means[label][1] == 1 else 's'})" for label in group)
                  for i, group in enumerate(table.groups, 1)]
        lines += [f"- {label}: {reason}" for label, reason in table.uncovered]
        lines.append("")
    return lines[:-1]


def end_budget_text(runs: list[Run]) -> str:
    """The budget the end-of-training comparisons use: "at N steps" where every run ended at N, else "at each run's
    last step"."""
    steps = last_steps(runs)
    return f"at {steps.pop():,} steps" if len(steps) == 1 else "at each run's last step"
