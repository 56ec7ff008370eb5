"""The report's sections per budget (``nerfexp.report.budgets``): report.md's "Per budget" (each variant against the
reference at each shared step and matched training time) and "At equal training time" (the variants ranked at a
few training times), and ``report_budgets.csv``, the same differences one per line."""

import csv
import io
import math
from collections.abc import Callable

from nerfexp.report.budgets import (
    METRICS,
    equal_time,
    equal_times,
    last_steps,
    scoring_seconds,
    seconds_text,
    step_differences,
    time_differences,
    time_window,
)
from nerfexp.report.comparison import Difference
from nerfexp.report.runs import Run
from nerfexp.report.shared_machines import timed_labels, timing_caveats
from nerfexp.report.variants import Variant

BUDGET_COLUMNS = ("variant", "reference", "metric", "kind", "budget", "n", "diff", "low", "high", "verdict")


def compared(variants: list[Variant], reference: Variant | None) -> list[Variant]:
    """The variants compared with ``reference``: the others with finished runs (none without a reference)."""
    if reference is None or not reference.finished:
        return []
    return [v for v in variants if v is not reference and v.finished]


def pair_times(variant: Variant, reference: Variant, times: list[float], timed: set[str]) -> list[float]:
    """The matched times of ``variant`` and ``reference``: those of ``times`` in the pair's ``time_window`` and its
    end (the shortest of their runs' totals), increasing; none where their times may not be compared (either is
    not in ``timed``, ``timed_labels``) or no time has a score of every run."""
    window = time_window([variant, reference])
    if window is None or not {variant.label, reference.label} <= timed:
        return []
    return sorted({t for t in times if window[0] <= t <= window[1]} | {window[1]})


def budget_rows(variants: list[Variant], reference: Variant | None) -> list[dict]:
    """report_budgets.csv's rows (``BUDGET_COLUMNS``): each compared variant - ``reference`` in each test score of
    ``METRICS``, at each shared step (kind step, budget: the step) and each matched time (kind time, budget: the
    seconds, ``equal_times``), with its number of seed pairs, 95% interval (NaN for fewer than two) and verdict."""
    times, timed = equal_times(variants)[1], timed_labels(variants)
    rows = []
    for variant in compared(variants, reference):
        for metric in METRICS:
            at_times = pair_times(variant, reference, times, timed)
            by_kind = (("step", step_differences(variant, reference, metric)),
                       ("time", time_differences(variant, reference, at_times, metric)))
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


# How report.md's budget sections are computed: said once, in its note on method (nerfexp.report.tables.method_text)
PER_BUDGET_METHOD = ("Per budget: at each step where every run of a variant and of the reference was scored, and at "
                     "training times (the fastest timed variant's budgets' mean times, its total the last, and the "
                     "shortest of the pair's runs' total), each run's test PSNR interpolated linearly between its "
                     "budgets where every run of both has one (never extrapolated). The budget verdict says where the "
                     "verdict depends on the budget, or is still moving between the last two steps.")
EQUAL_TIME_METHOD = ("At equal training time: at the fastest timed variant's total and its budgets' times, each "
                     "variant's test PSNR interpolated linearly between its runs' budgets (never extrapolated), the "
                     "mean over its runs that have one, ranked in groups as the ranking is.")
NOT_BY_TIME = "the note on times, below the table, says why"  # where a caveat keeps variants from time comparisons


def per_budget_text(variants: list[Variant], reference: Variant | None, words: dict[str, str]) -> list[str]:
    """report.md's "Per budget" section: one row per compared variant, a column per step any pair shares and per
    matched time (``equal_times``; none where no variant is timed), each cell the PSNR difference to ``reference``
    with its 95% interval, and the variant's budget ``words`` (label -> ``budget_words``)."""
    lines = ["## Per budget", ""]
    variants_compared = compared(variants, reference)
    if not variants_compared:
        return lines + ["No per-budget differences: they need a reference variant with finished runs and another "
                        "variant to compare with it."]
    fastest, times = equal_times(variants)
    timed = timed_labels(variants)
    steps = {v.label: step_differences(v, reference) for v in variants_compared}
    at_times = {v.label: time_differences(v, reference, pair_times(v, reference, times, timed))
                for v in variants_compared}
    columns = sorted({step for differences in steps.values() for step in differences})
    ends = {v.label: window[1] if (window := time_window([v, reference])) else None for v in variants_compared}
    lines += [f"Test PSNR - reference (`{reference.label}`), dB, paired by seed, with its 95% interval, at each step "
              "both were scored at" + (" and at matched training times" if fastest else "") + "; – : not shared."
              + ("" if (scoring := scoring_seconds(variants)) is None else
                 f" Scoring the budgets before the end took {seconds_text(scoring)} a run on average, outside "
                 "the training times.")
              + ("" if fastest else f" By step only: {NOT_BY_TIME}."), ""]
    time_header = [*(f"at {seconds_text(t)}" for t in times), "at the pair's shortest run's total"] if fastest else []
    header = ["variant", *(f"at {step:,} steps" for step in columns), *time_header, "budget verdict"]
    lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for variant in variants_compared:
        differences = at_times[variant.label]
        time_cells = [*(cell(differences.get(t)) for t in times), end_cell(differences, ends[variant.label])]
        cells = [variant.label, *(cell(steps[variant.label].get(step)) for step in columns),
                 *(time_cells if fastest else []),
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
    test PSNR, those the seeds do not resolve on one line (``equal_time``), and those with no score there; one
    line where no variant is timed."""
    lines = ["## At equal training time", ""]
    fastest, times = equal_times(variants)
    if fastest is None:
        why = NOT_BY_TIME if timing_caveats(variants) else "no variant has finished runs with their training times"
        return lines + [f"No ranking at equal training time: {why}."]
    untimed = [v.label for v in variants if v.finished and v.label not in timed_labels(variants)]
    lines += [f"What is best for a given time on this machine: the variants at the fastest one's (`{fastest.label}`) "
              "budgets' times, ranked by mean test PSNR; those on one line are not resolved from its first."
              + (f" Not ranked, compared by step only ({NOT_BY_TIME}): {', '.join(untimed)}." if untimed else ""), ""]
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
