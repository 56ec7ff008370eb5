"""The report's tables: ``report.md`` (the result first: the variants with their differences to the reference and
verdicts, what the numbers need said below them, each once; the published figures where they apply, the ranking, the
paper's order, the comparisons per budget, the jobs that did not finish; last how it was computed) and
``report.csv``."""


import csv
import io
import json
import math
from dataclasses import dataclass
from pathlib import Path

from nerfexp.reading import UnreadableFile
from nerfexp.report.budget_tables import (
    EQUAL_TIME_METHOD,
    PER_BUDGET_METHOD,
    end_budget_text,
    equal_time_text,
    per_budget_text,
)
from nerfexp.report.budgets import budget_words, step_differences
from nerfexp.report.comparison import Difference, compare_order, tiers
from nerfexp.report.publication_tables import (
    PUBLISHED_COLUMNS,
    published_columns,
    published_method,
    published_text,
    variant_beside,
)
from nerfexp.report.publications import PAPER_ABLATION
from nerfexp.report.runs import Run, run_precision
from nerfexp.report.shared_machines import machines, timing_caveats
from nerfexp.report.variants import Variant, difference
from nerfexp.rundir.layout import DIFFERENCE_PLOT, PARETO_PLOT, PSNR_PLOT, planned_jobs


def _fmt(value: float, digits: int) -> str:
    return "–" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def _pm(variant: Variant, key: str, digits: int) -> str:
    mean, std = variant.mean(key), variant.std(key)
    return _fmt(mean, digits) + ("" if not math.isfinite(std) else f" ± {std:.{digits}f}")


COLUMNS = ("variant", "runs", "finished", "test_psnr_mean", "test_psnr_std", "test_ssim_mean", "test_ssim_std",
           "test_lpips_mean", "test_lpips_std",
           "reference", "paired_seeds", "psnr_diff", "psnr_diff_low", "psnr_diff_high",
           "ssim_diff", "ssim_diff_low", "ssim_diff_high", "lpips_diff", "lpips_diff_low", "lpips_diff_high", "verdict",
           "budget_verdict",
           "train_time_s", "time_per_step_s", "rays_per_s", "n_params", "evaluations_per_ray",
           *PUBLISHED_COLUMNS, "precision", "tags", "notes")


# The test scores compared with the reference: higher PSNR and SSIM are better, lower LPIPS (AlexNet's, which
# runs without its weights do not have: NaN in report.csv, no column in report.md where no run has it).
METRICS = ("psnr", "ssim", "lpips")


def reference_differences(variant: Variant, reference: Variant | None) -> dict[str, Difference]:
    """``variant`` - ``reference`` in each test score of ``METRICS``, paired by seed (``difference``); none
    for the reference itself, or without one."""
    if reference is None or variant is reference:
        return {}
    return {metric: difference(variant, reference, f"test_{metric}") for metric in METRICS}


def reference_columns(differences: dict[str, Difference], reference: Variant | None) -> dict:
    """The CSV's columns of a variant's ``differences`` to ``reference`` (``reference_differences``): PSNR,
    SSIM and LPIPS differences paired by seed, their 95% intervals (NaN for fewer than two seeds, or
    none where a side has no LPIPS) and the PSNR verdict."""
    if not differences:
        return {"reference": "" if reference is None else "reference", "paired_seeds": "", "verdict": "",
                "budget_verdict": "",
                **{f"{m}_diff{end}": math.nan for m in METRICS for end in ("", "_low", "_high")}}
    columns = {"reference": reference.label}
    for metric, d in differences.items():
        low, high = d.interval or (math.nan, math.nan)
        columns.update({f"{metric}_diff": d.mean, f"{metric}_diff_low": low, f"{metric}_diff_high": high})
        if metric == "psnr":
            columns.update(paired_seeds=d.n, verdict=d.verdict_text())
    return columns


def budget_verdict(variant: Variant, reference: Variant | None) -> str:
    """What ``variant``'s PSNR verdict against ``reference`` needs said of its budgets (``budget_words`` of its
    differences at each shared step); "" where nothing, and for the reference itself or without one."""
    if reference is None or variant is reference or not variant.finished:
        return ""
    return budget_words(step_differences(variant, reference))


def table_rows(variants: list[Variant], reference: Variant | None = None) -> list[dict]:
    """One dict per variant with the ``COLUMNS``, and its ``differences`` to the reference (computed once,
    for report.md's cells and report.csv's columns); the published figure beside it only where one applies
    (``nerfexp.report.publication_tables.variant_beside``). Its tags and notes (``Variant.tags``, ``Variant.notes``)
    are JSON lists of texts."""
    rows = []
    for v in variants:
        differences = reference_differences(v, reference)
        rows.append({"variant": v.label, "runs": len(v.runs), "finished": len(v.finished),
                     "test_psnr_mean": v.mean("test_psnr"), "test_psnr_std": v.std("test_psnr"),
                     "test_ssim_mean": v.mean("test_ssim"), "test_ssim_std": v.std("test_ssim"),
                     "test_lpips_mean": v.mean("test_lpips"), "test_lpips_std": v.std("test_lpips"),
                     **reference_columns(differences, reference), "budget_verdict": budget_verdict(v, reference),
                     "train_time_s": v.mean("train_time_s"), "time_per_step_s": v.mean("time_per_step_s"),
                     "rays_per_s": v.mean("rays_per_s"), "n_params": v.mean("n_params"),
                     "evaluations_per_ray": v.mean("evaluations_per_ray"), **published_columns(variant_beside(v)),
                     "precision": v.precision, "tags": json.dumps(v.tags), "notes": json.dumps(v.notes),
                     "differences": differences})
    return rows


def ranking_text(variants: list[Variant]) -> list[str]:
    """The ranking by mean test PSNR, cut into groups whose members the seeds do not resolve from the
    group's best (``nerfexp.report.comparison.tiers``), then the pairs of ablation rows against the paper's order."""
    ranked = [v for v in variants if v.finished]
    by_label = {v.label: v for v in ranked}
    groups = tiers([v.label for v in ranked], lambda a, b: difference(by_label[a], by_label[b]))
    lines = ["## Ranking by mean test PSNR", "",
             "Variants on one line are not resolved from the first of the line by these seeds.", ""]
    lines += [f"{i}. " + ", ".join(f"{label} ({by_label[label].mean('test_psnr'):.2f} dB)" for label in group)
              for i, group in enumerate(groups, 1)]
    return lines + [""] + paper_order_text(ranked)


def paper_order_text(ranked: list[Variant]) -> list[str]:
    """Each pair of the paper's ablation rows in the sweep: resolved in the paper's order, resolved in
    the other, or not resolved with the seeds there are; each pair named with our difference."""
    in_paper = [v for v in ranked if v.choice("ablation") in PAPER_ABLATION]
    rows = {v.choice("ablation"): v for v in in_paper}
    if len(rows) < 2 or len(in_paper) != len(rows):
        return ["No comparison with the paper's order: it needs at least two finished variants that are "
                "distinct rows of the paper's ablation table (`ablation=...`)."]
    paper_order = sorted(rows, key=lambda n: -PAPER_ABLATION[n][1])

    def measured(higher: str, lower: str) -> Difference:
        return difference(rows[higher], rows[lower])

    order = compare_order(paper_order, measured)
    n_pairs = len(rows) * (len(rows) - 1) // 2
    at = end_budget_text([run for v in rows.values() for run in v.finished])
    pairs_text = f"{n_pairs} pair{'' if n_pairs == 1 else 's'}"
    lines = [f"## Against the paper's order ({len(rows)} ablation rows, {pairs_text})", "",
             f"Compared at the end of training, {at} (the \"Per budget\" section has the earlier budgets). "
             f"Of the {pairs_text} the paper orders: {len(order.agree)} resolved in the paper's order, "
             f"{len(order.reversed)} resolved in the other order, {len(order.unresolved)} not resolved by "
             "these seeds. Each pair: the paper's higher row first, then our mean difference (higher - lower) "
             "in test PSNR, paired by seed, with its 95% interval.", ""]
    for title, pairs in (("Resolved in the paper's order", order.agree),
                         ("Resolved in the other order", order.reversed),
                         ("Not resolved", order.unresolved)):
        lines += [f"**{title}** ({len(pairs)}):", ""]
        lines += [f"- {PAPER_ABLATION[a][0]} above {PAPER_ABLATION[b][0]}: {measured(a, b).describe(2)} dB"
                  for a, b in pairs] or ["- none"]
        lines.append("")
    return lines[:-1]


def precision_text(variants: list[Variant]) -> tuple[str, bool]:
    """What the finished runs trained in, and whether they differ (then report.md gives each variant's)."""
    seen = sorted({run_precision(run.results) for v in variants for run in v.finished})
    if len(seen) <= 1:
        return (f"Every run trained in {seen[0]} precision." if seen else ""), False
    mixed = [v.label for v in variants if len({run_precision(run.results) for run in v.finished}) > 1]
    text = (f"Runs trained in different precisions ({', '.join(seen)}): the precision column says which, and "
            "differences between them are partly the precision's.")
    if mixed:
        text += f" Variants whose own runs differ in precision: {'; '.join(mixed)}."
    return text, True


@dataclass(frozen=True)
class Shown:
    """Which of report.md's optional columns its table has: ``tags`` (some variant has tags), ``lpips`` (some run
    scored it), ``precision`` (the runs' precisions differ) and the differences to a ``reference``."""

    tags: bool
    lpips: bool
    precision: bool
    reference: bool


def shown_columns(variants: list[Variant], reference: Variant | None) -> Shown:
    return Shown(any(v.tags for v in variants), any(v.values("test_lpips") for v in variants),
                 precision_text(variants)[1], reference is not None)


def table_header(shown: Shown) -> list[str]:
    """report.md's table's column names."""
    header = ["variant", *(["tags"] if shown.tags else []), "runs", "test PSNR (dB)", "test SSIM"]
    header += ["test LPIPS"] if shown.lpips else []
    header += ["precision"] if shown.precision else []
    if shown.reference:
        header += ["PSNR - reference (95% CI)", "SSIM - reference (95% CI)"]
        header += ["LPIPS - reference (95% CI; lower is better)"] if shown.lpips else []
        header += ["verdict (PSNR)"]
    return header + ["train time (s)", "s / step", "rays / s", "params", "evals / ray"]


def reference_cells(v: Variant, row: dict, reference: Variant, lpips: bool) -> list[str]:
    """A variant's differences to ``reference`` and its verdict, as report.md's cells."""
    if v is reference or not v.finished:
        return ["reference" if v is reference else "–"] * (4 if lpips else 3)
    differences = row["differences"]
    cells = [differences["psnr"].describe(2), differences["ssim"].describe(3)]
    if lpips:
        cells.append(differences["lpips"].describe(3) if differences["lpips"].n else "–")  # none: a side has none
    return cells + [row["verdict"] + (f" ({row['budget_verdict']})" if row["budget_verdict"] else "")]


def table_cells(v: Variant, row: dict, shown: Shown, reference: Variant | None) -> list[str]:
    """A variant's line of report.md's table (``table_header``'s columns) from its ``row`` (``table_rows``)."""
    cells = [row["variant"], *([", ".join(map(markdown_text, v.tags))] if shown.tags else []),
             f"{row['finished']}/{row['runs']}", _pm(v, "test_psnr", 2), _pm(v, "test_ssim", 3)]
    cells += [_pm(v, "test_lpips", 3)] if shown.lpips else []
    cells += [row["precision"]] if shown.precision else []
    cells += reference_cells(v, row, reference, shown.lpips) if reference is not None else []
    return cells + [_fmt(row["train_time_s"], 0), _fmt(row["time_per_step_s"], 4), _fmt(row["rays_per_s"], 0),
                    _fmt(row["n_params"], 0), _fmt(row["evaluations_per_ray"], 0)]


def table_text(variants: list[Variant], rows: list[dict], reference: Variant | None) -> list[str]:
    """report.md's table: a line per variant, its scores, differences to ``reference`` with the verdicts, and costs."""
    shown = shown_columns(variants, reference)
    header = table_header(shown)
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return lines + ["| " + " | ".join(table_cells(v, row, shown, reference)) + " |" for v, row in zip(variants, rows)]


def table_notes(variants: list[Variant], protocols: str) -> list[str]:
    """What the table's numbers need said, each once, below it: which scores these are (``protocols``), the
    precisions where they differ, LPIPS's network, the caveats on its times (``timing_caveats``) and the runs'
    notes."""
    precisions, mixed = precision_text(variants)
    notes = [protocols, precisions if mixed else ""]
    if any(v.values("test_lpips") for v in variants):
        notes.append("LPIPS is AlexNet's (v0.1; lower is more alike), on the runs that scored it (docs/metrics.md); "
                     "a paper's LPIPS is VGG's, on another scale, and is not compared.")
    notes += timing_caveats(variants)
    lines = [line for note in notes if note for line in ("", note)]
    if any(v.notes for v in variants):
        lines += ["", "Notes of the variants' runs:", ""]
        lines += [f"- {v.label}: {markdown_text(note)}" for v in variants for note in v.notes]
    return lines


def summary_text(variants: list[Variant], runs: list[Run], sources: list[Path], reference: Variant | None) -> str:
    """The report's first line: its runs, where from, and the reference variant (or why there is none)."""
    complete = sum(v.choice("ablation") == "complete" for v in variants if v.finished)
    why = "the sweep has no `ablation=complete`" if not complete else f"{complete} variants are `ablation=complete`"
    compared = (f"Reference: `{reference.label}`." if reference is not None else
                f"No reference variant ({why}; name one with `--reference VARIANT`), so no differences between "
                "variants are given.")
    return f"Runs: {states_text(runs)} from {', '.join(f'`{s}`' for s in sources)}. {compared}"


def unfinished_text(runs: list[Run], sources: list[Path]) -> list[str]:
    """report.md's list of the jobs that did not finish, collapsed, have no test score or are damaged (each with
    why), and of the jobs ``sources``' sweeps planned that never started."""
    planned, unplanned = [], []
    for source in sources:
        try:
            planned.append((source, planned_jobs(source)))
        except UnreadableFile as error:  # costs the report the planned count, not the report
            unplanned.append(f"`{error.path}` not read ({error.reason}): how many jobs the sweep planned is unknown")
    started = {source: sum(source in run.path.parents for run in runs) for source in sources}
    not_started = [f"`{source}` plans {n} jobs, {started[source]} started" for source, n in planned
                   if n is not None and n > started[source]]
    unfinished = [run for run in runs if run.state != "finished"]
    lines = ["## Jobs that did not finish, collapsed or have no test score, or whose files are damaged "
             "(not counted)", ""]
    lines += [f"- `{run.path}` ({overrides_text(run.overrides)}): {run.state}"
              + (f": {run.detail}" if run.detail else "") for run in unfinished]
    lines += [f"- {text}: the rest never started (the sweep stopped or is still going)" for text in not_started]
    lines += [f"- {text}" for text in unplanned]
    return lines + (["None."] if not unfinished and not not_started and not unplanned else [])


def machines_text(variants: list[Variant]) -> str:
    """How the times were measured, and where: the machine, where there is one (several: the note on times names
    them)."""
    found = machines(variants)
    where = "each run's machine" if len(found) != 1 else "{}: {}".format(*found[0])
    return (f"Times are training wall-clock seconds as each run measured them (periodic validation included; "
            f"preparing the data and the final test not), on {where}.")


def method_text(variants: list[Variant], reference: Variant | None) -> list[str]:
    """report.md's last section: how its numbers were computed, each method once."""
    over = ", ".join(variants[0].over) if variants else "seed"
    precisions, mixed = precision_text(variants)
    method = [f"A variant is the runs whose overrides differ only in {over} (and their tags, notes and test "
              "budgets); its scores are the mean ± sample standard deviation over its finished runs. "
              + machines_text(variants) + ("" if mixed or not precisions else f" {precisions}")]
    if reference is not None:
        method.append("Differences to the reference: the mean over the pairs of runs of (variant - reference), each "
                      f"run paired with the reference's run of the same {over}, with its 95% confidence interval "
                      "(Student's t, n - 1 degrees of freedom; n: the pairs, the seeds where only seeds are averaged "
                      "over). Verdict: better or worse where the interval excludes zero, else not "
                      "resolved with this many seeds; one seed gives no interval. Intervals are per comparison, not "
                      "corrected for making many.")
    method += ["Ranking: variants by mean test PSNR, cut into groups: a group starts at its best and takes each next "
               "variant whose difference to it, paired by seed, has a 95% interval that includes zero (or no "
               "interval, with one seed).",
               PER_BUDGET_METHOD, EQUAL_TIME_METHOD, *published_method(variants),
               f"Plots: `{PSNR_PLOT}` (validation PSNR against training seconds: each variant's mean over seeds, its "
               f"band from the lowest to the highest seed, single runs faint), `{PARETO_PLOT}` (test PSNR against "
               "total training time, bars one standard deviation over seeds; each variant's budgets as small points "
               f"joined by a thin line), `{DIFFERENCE_PLOT}` (each variant's test PSNR - the reference's against "
               "training time at the matched times, its 95% interval as a band)."]
    return ["## How these numbers were computed", "", *(f"- {text}" for text in method)]


def markdown(variants: list[Variant], rows: list[dict], runs: list[Run], sources: list[Path],
             reference: Variant | None = None, protocols: str = "") -> str:
    """report.md, the result first: its runs and reference (``summary_text``), the table of the ``variants`` with
    their ``rows`` (``table_rows`` against ``reference``) and verdicts, and below it what its numbers need said, each
    once (``table_notes``; ``protocols``: which scores these are, where it needs saying, ``compared_runs`` and
    ``vouched_lpips``); then the published figures where they apply, the ranking and the paper's order, the
    comparisons per budget and at equal time, and the jobs that did not finish; last, how it was computed
    (``method_text``)."""
    lines = ["# nerfexp report", "", summary_text(variants, runs, sources, reference), "",
             *table_text(variants, rows, reference), *table_notes(variants, protocols)]
    words = {row["variant"]: row["budget_verdict"] for row in rows}
    for section in (published_text(variants), ranking_text(variants), per_budget_text(variants, reference, words),
                    equal_time_text(variants), unfinished_text(runs, sources), method_text(variants, reference)):
        lines += ["", *section] if section else []
    return "\n".join(lines) + "\n"


STATES = ("finished", "collapsed", "not scored", "failed", "killed", "running", "damaged", "unknown")  # Run.state


def states_text(runs: list[Run]) -> str:
    """How many ``runs`` there are, and in which states (in ``STATES``' order): "7 (5 finished, 2 damaged)"."""
    states = {state: n for state in STATES if (n := sum(run.state == state for run in runs))}
    return f"{len(runs)} ({', '.join(f'{n} {state}' for state, n in states.items())})"


MARKUP = str.maketrans({c: f"\\{c}" for c in "\\`*_[]|"})  # what Markdown would read as markup in a cell


def markdown_text(text: str) -> str:
    """A tag or a note as report.md writes it: shown as typed, its Markdown characters escaped (a ``|`` would
    end a table's cell, ``*`` start emphasis)."""
    return text.translate(MARKUP)


def overrides_text(overrides: list[str] | None) -> str:
    """A job's overrides as the report lists them."""
    if overrides is None:
        return "overrides unreadable"
    return ", ".join(overrides) or "no overrides"


# A text cell starting with one of these is a formula to a spreadsheet (=, +, -, @) or may become one once
# the spreadsheet strips it (tab, carriage return): OWASP's CSV injection guidance
FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")


def csv_cell(value: object) -> object:
    """``value`` as report.csv writes it: a text starting with one of ``FORMULA_STARTS`` (a label such as
    ``=HYPERLINK(...)`` or ``-lr``) prefixed with ``'``, which spreadsheets read as "this cell is text", so
    that opening the file runs nothing; numbers, negative ones included, stay numbers."""
    return f"'{value}" if isinstance(value, str) and value.startswith(FORMULA_STARTS) else value


def csv_text(rows: list[dict]) -> str:
    """report.csv: the ``COLUMNS`` of each of ``rows`` (``table_rows``), text cells made safe to open in a
    spreadsheet (``csv_cell``) and quoted, so that a carriage return in a label stays in its cell."""
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=COLUMNS, lineterminator="\n", quoting=csv.QUOTE_NONNUMERIC)
    writer.writeheader()
    writer.writerows({column: csv_cell(row[column]) for column in COLUMNS} for row in rows)
    return out.getvalue()
