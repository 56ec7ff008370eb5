"""``nerfexp-report``: a sweep's variants side by side, their quality against the compute they cost.

Reads every run under the given directories (a run is a folder holding ``status.json`` or
``results.json``, as ``nerfexp`` writes them), groups runs into variants and writes

- ``report.md`` / ``report.csv``: one row per variant: test PSNR and SSIM (mean and sample standard
  deviation over the runs of the variant, usually its seeds), the difference to a reference variant
  paired by seed with its 95% interval and verdict (``nerfexp.comparison``), training time, time per
  step, rays/s, parameters, network evaluations per ray, and for rows of the paper's ablation table
  the paper's numbers beside ours; then the ranking in groups the seeds cannot tell apart, and which
  pairs of ablation rows agree with the paper's order, are reversed, or are not resolved; then every
  job that did not finish (failed, or running / killed) with its reason, and every run whose files
  cannot be read (damaged: the file and why), none of whose numbers is used;
- ``psnr_vs_time.png``: validation PSNR against training wall-clock seconds: each variant's mean over
  seeds with a band from the lowest to the highest seed, single runs faint;
- ``pareto.png``: final test PSNR against total training time (bars: one standard deviation over
  seeds), the Pareto front drawn through the means;
- ``report.html``: all of the above as a page that opens from disk (``nerfexp.report_page``), and a few
  test views (``--views``) rendered by each variant beside the ground truth, with the render's error
  image and its PSNR and SSIM; its pictures in ``report_images/``, decoded from the runs' ``test/``
  PNGs and written anew.

The reference is the paper's complete model (``ablation=complete``) where the sweep has it, else the
variant named by ``--reference``; without either the report has no differences.

A variant is the set of a run's command-line overrides without the keys averaged over (``--over``,
default ``seed``), leaving out overrides every run shares.
"""

import argparse
import csv
import io
import math
import socket
import statistics
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch
from matplotlib import colormaps
from matplotlib.figure import Figure
from torch import Tensor

from nerfexp.arguments import command_parser
from nerfexp.comparison import Difference, compare_order, paired_difference, seeds, tiers
from nerfexp.console import one_line_errors
from nerfexp.data.images import read_image
from nerfexp.errors import DatasetError, NerfexpError
from nerfexp.files import TEMPORARY, atomic_directory, atomic_write, folder_entries, foreign_message, is_made
from nerfexp.pixels import png_bytes
from nerfexp.report_page import Picture, Tile, page_html
from nerfexp.rundir import (
    METRICS,
    REPORT_MADE,
    RESULTS,
    RUN_MADE,
    STATUS,
    SWEEP_MADE,
    find_run_dirs,
    planned_jobs,
    process_alive,
    read_json,
    read_metrics,
)

# The paper's Table 4 (mean over the 8 Realistic Synthetic scenes): conf/ablation/NAME -> (row, PSNR, SSIM).
PAPER_ABLATION = {
    "no_pe_vd_h": ("No PE, VD, H", 26.67, 0.906),
    "no_posenc": ("No Pos. Encoding", 28.77, 0.924),
    "no_view_dependence": ("No View Dependence", 27.66, 0.925),
    "no_hierarchical": ("No Hierarchical", 30.06, 0.938),
    "far_fewer_images": ("Far Fewer Images", 27.78, 0.925),
    "fewer_images": ("Fewer Images", 29.79, 0.940),
    "fewer_frequencies": ("Fewer Frequencies", 30.59, 0.944),
    "more_frequencies": ("More Frequencies", 30.81, 0.946),
    "complete": ("Complete Model", 31.01, 0.947),
}


@dataclass
class Run:
    """One job's directory and what it left: ``state`` is finished, failed, running or killed."""

    path: Path
    state: str
    overrides: list[str] | None  # None: a damaged job whose overrides cannot be read
    detail: str = ""
    results: dict | None = None
    curve: list[tuple[int, float, float]] = field(default_factory=list)  # (step, wall seconds, validation PSNR)


@dataclass
class Variant:
    """Runs that differ only in the override keys ``over`` (their seeds): ``by_seed`` pairs them with
    another variant's runs."""

    label: str
    runs: list[Run]
    over: tuple[str, ...] = ("seed",)

    @property
    def finished(self) -> list[Run]:
        return [run for run in self.runs if run.state == "finished"]

    def values(self, key: str) -> list[float]:
        return [run.results[key] for run in self.finished if run.results.get(key) is not None]

    def mean(self, key: str) -> float:
        values = self.values(key)
        return statistics.fmean(values) if values else math.nan

    def std(self, key: str) -> float:
        """Sample standard deviation (n - 1); NaN for fewer than two runs."""
        values = self.values(key)
        return statistics.stdev(values) if len(values) > 1 else math.nan

    def by_seed(self, key: str) -> dict[tuple[str, ...], float]:
        """``results[key]`` of each finished run, keyed by the run's overrides of the ``over`` keys."""
        return {tuple(sorted(o for o in run.overrides if _key(o) in self.over)): run.results[key]
                for run in self.finished if run.results.get(key) is not None}

    def choice(self, key: str):
        """The variant's choice of a config group, where all its finished runs agree."""
        values = {run.results["choices"].get(key) for run in self.finished}
        return values.pop() if len(values) == 1 else None

    @property
    def paper(self) -> tuple[str, float, float] | None:
        return PAPER_ABLATION.get(self.choice("ablation"))


class Damaged(Exception):
    """A run's file that cannot be read as nerfexp writes it; the message names the file and why."""


def read_record(path: Path, required: tuple[str, ...]) -> dict | None:
    """A run's JSON file (None where there is none) holding the keys ``required``, else ``Damaged``."""
    try:
        record = read_json(path)
    except (ValueError, OSError) as error:  # truncated, empty, not UTF-8, unreadable
        raise Damaged(f"{path.name}: not readable as JSON ({error})") from None
    if record is not None and not (isinstance(record, dict) and all(key in record for key in required)):
        raise Damaged(f"{path.name}: not a record with {', '.join(required)}")
    return record


def read_curve(path: Path, ended: bool) -> list[tuple[int, float, float]]:
    """(step, wall seconds, validation PSNR) of each validation in a run's ``metrics.jsonl``, else
    ``Damaged``; a last line cut short is damage where the run has ``ended`` (``read_metrics``)."""
    try:
        return [(record["step"], record["wall_time_s"], record["psnr"])
                for record in read_metrics(path, ended) if record["split"] == "val"]
    except (ValueError, OSError) as error:
        raise Damaged(f"{METRICS}: {error}") from None
    except (KeyError, TypeError):
        raise Damaged(f"{METRICS}: a record without step, wall_time_s, split and psnr") from None


def job_overrides(path: Path) -> list[str] | None:
    """A job's command-line overrides, from whichever of its ``status.json`` and ``results.json`` can be
    read (each records them), so that a job with another file damaged still counts against its variant;
    None where neither can."""
    for name in (STATUS, RESULTS):
        try:
            record = read_record(path / name, ())
        except Damaged:
            continue
        overrides = (record or {}).get("overrides")
        if isinstance(overrides, list) and all(isinstance(o, str) for o in overrides):
            return overrides
    return None


def read_run(path: Path) -> Run:
    """What a run directory says about its job. A job whose status still says running but whose
    process is gone from this host was killed (out of memory, a time limit, a signal). A run with a file
    that cannot be read as nerfexp writes it (``Damaged``) is listed as damaged with its overrides where
    they can be read (``job_overrides``; else none, and it joins no variant), and none of its numbers is
    used."""
    try:
        status = read_record(path / STATUS, ("state",)) or {}
        results = read_record(path / RESULTS, ("test_psnr", "test_ssim", "choices"))
    except Damaged as damage:
        return Run(path, "damaged", job_overrides(path), str(damage))
    overrides = status.get("overrides", (results or {}).get("overrides", []))
    state = status.get("state", "finished" if results is not None else "unknown")
    detail = status.get("error", "")
    if state == "finished" and results is None:
        state, detail = "failed", f"status says finished but {RESULTS} is missing"
    if state == "running":
        here, pid = status.get("host") == socket.gethostname(), status.get("pid")
        if here and pid is not None and not process_alive(pid, status.get("process_start")):
            state, detail = "killed", f"process {pid} is gone (killed before it finished)"
        else:
            detail = f"on {status.get('host')}, process {pid}" + ("" if here else " (not checked)")
    try:
        curve = read_curve(path, ended=state != "running")
    except Damaged as damage:
        ended = "" if state == "finished" else f" (the job {state}" + (f": {detail})" if detail else ")")
        return Run(path, "damaged", list(overrides), f"{damage}{ended}")
    return Run(path, state, list(overrides), detail, results if state == "finished" else None, curve)


def find_runs(directories: list[Path]) -> list[Run]:
    """Every run directory under ``directories`` (a run directory itself counts)."""
    paths = set()
    for directory in directories:
        if not directory.is_dir():
            raise SystemExit(f"nerfexp-report: error: {directory} is not a directory")
        paths.update(find_run_dirs(directory))
    if not paths:
        raise SystemExit(f"nerfexp-report: error: no runs (no {STATUS} or {RESULTS}) under "
                         f"{', '.join(map(str, directories))}")
    return [read_run(path) for path in sorted(paths)]


def _key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("+~")


def group_variants(runs: list[Run], over: tuple[str, ...] = ("seed",)) -> list[Variant]:
    """Runs with the same overrides, apart from the keys in ``over``, form a variant: every job started,
    damaged, failed or still running included, so that a variant counts its finished runs against all of
    them. Overrides that every run shares are left out of the labels. Variants are ranked by mean test PSNR."""
    kept = [tuple(o for o in run.overrides if _key(o) not in over) for run in runs]
    shared = set.intersection(*(set(k) for k in kept)) if kept else set()
    groups: dict[frozenset, tuple[tuple, list[Run]]] = {}  # the order of overrides does not matter
    for key, run in zip(kept, runs):
        groups.setdefault(frozenset(key), (key, []))[1].append(run)
    variants = []
    for key, members in groups.values():
        label = ", ".join(o for o in key if o not in shared) or ", ".join(key) or "default"
        variants.append(Variant(label, members, tuple(over)))
    return sorted(variants, key=lambda v: (-v.mean("test_psnr") if v.finished else math.inf, v.label))


def reference_variant(variants: list[Variant], name: str | None = None) -> Variant | None:
    """The variant the others are compared with: the one named ``name`` (its label, or its overrides in
    any order), else the paper's complete model (``ablation=complete``) if one variant is, else None."""
    if name is not None:
        wanted = frozenset(part.strip() for part in name.split(","))
        for variant in variants:
            if frozenset(part.strip() for part in variant.label.split(",")) == wanted:
                return variant
        raise SystemExit(f"nerfexp-report: error: --reference {name!r}: no such variant; the variants are "
                         + "; ".join(repr(v.label) for v in variants))
    complete = [v for v in variants if v.finished and v.choice("ablation") == "complete"]
    return complete[0] if len(complete) == 1 else None


def difference(a: Variant, b: Variant, key: str = "test_psnr") -> Difference:
    """a - b in ``key``, paired by seed (``nerfexp.comparison.paired_difference``)."""
    return paired_difference(a.by_seed(key), b.by_seed(key))


def _fmt(value: float, digits: int) -> str:
    return "–" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def _pm(variant: Variant, key: str, digits: int) -> str:
    mean, std = variant.mean(key), variant.std(key)
    return _fmt(mean, digits) + ("" if not math.isfinite(std) else f" ± {std:.{digits}f}")


COLUMNS = ("variant", "runs", "finished", "test_psnr_mean", "test_psnr_std", "test_ssim_mean", "test_ssim_std",
           "reference", "paired_seeds", "psnr_diff", "psnr_diff_low", "psnr_diff_high",
           "ssim_diff", "ssim_diff_low", "ssim_diff_high", "verdict",
           "train_time_s", "time_per_step_s", "rays_per_s", "n_params", "evaluations_per_ray",
           "paper_row", "paper_psnr", "paper_ssim", "psnr_minus_paper")


def reference_columns(variant: Variant, reference: Variant | None) -> dict:
    """The CSV's columns of ``variant`` against ``reference``: PSNR and SSIM differences paired by seed,
    their 95% intervals (NaN for fewer than two seeds) and the PSNR verdict."""
    if reference is None or variant is reference:
        return {"reference": "" if reference is None else "reference", "paired_seeds": "", "verdict": "",
                **{f"{m}_diff{end}": math.nan for m in ("psnr", "ssim") for end in ("", "_low", "_high")}}
    columns = {"reference": reference.label}
    for metric in ("psnr", "ssim"):
        d = difference(variant, reference, f"test_{metric}")
        low, high = d.interval or (math.nan, math.nan)
        columns.update({f"{metric}_diff": d.mean, f"{metric}_diff_low": low, f"{metric}_diff_high": high})
        if metric == "psnr":
            columns.update(paired_seeds=d.n, verdict=d.verdict_text())
    return columns


def table_rows(variants: list[Variant], reference: Variant | None = None) -> list[dict]:
    """One dict per variant with the ``COLUMNS``; the difference to the paper only on Blender data
    (the paper's numbers are means over its 8 Blender scenes; other scenes are not comparable)."""
    rows = []
    for v in variants:
        paper = v.paper
        row = {"variant": v.label, "runs": len(v.runs), "finished": len(v.finished),
               "test_psnr_mean": v.mean("test_psnr"), "test_psnr_std": v.std("test_psnr"),
               "test_ssim_mean": v.mean("test_ssim"), "test_ssim_std": v.std("test_ssim"),
               **reference_columns(v, reference),
               "train_time_s": v.mean("train_time_s"), "time_per_step_s": v.mean("time_per_step_s"),
               "rays_per_s": v.mean("rays_per_s"), "n_params": v.mean("n_params"),
               "evaluations_per_ray": v.mean("evaluations_per_ray"),
               "paper_row": paper[0] if paper else "", "paper_psnr": paper[1] if paper else math.nan,
               "paper_ssim": paper[2] if paper else math.nan, "psnr_minus_paper": math.nan}
        if paper and v.choice("data") == "blender":
            row["psnr_minus_paper"] = row["test_psnr_mean"] - paper[1]
        rows.append(row)
    return rows


def ranking_text(variants: list[Variant]) -> list[str]:
    """The ranking by mean test PSNR, cut into groups whose members the seeds do not resolve from the
    group's best (``nerfexp.comparison.tiers``), then the pairs of ablation rows against the paper's order."""
    ranked = [v for v in variants if v.finished]
    by_label = {v.label: v for v in ranked}
    groups = tiers([v.label for v in ranked], lambda a, b: difference(by_label[a], by_label[b]))
    lines = ["## Ranking by mean test PSNR", "",
             "Variants on one line are not resolved from the first of the line: the 95% interval of their "
             "difference in test PSNR, paired by seed, includes zero (or there is no interval, with one "
             "seed). The next line starts at the first variant resolved below it.", ""]
    lines += [f"{i}. " + ", ".join(f"{label} ({by_label[label].mean('test_psnr'):.2f} dB)" for label in group)
              for i, group in enumerate(groups, 1)]
    return lines + [""] + paper_order_text(ranked)


def paper_order_text(ranked: list[Variant]) -> list[str]:
    """Each pair of the paper's ablation rows in the sweep: resolved in the paper's order, resolved in
    the other, or not resolved with the seeds there are; each pair named with our difference."""
    rows = {v.choice("ablation"): v for v in ranked if v.paper}
    if len(rows) < 2 or sum(bool(v.paper) for v in ranked) != len(rows):
        return ["No comparison with the paper's order: it needs at least two finished variants that are "
                "distinct rows of the paper's ablation table (`ablation=...`)."]
    paper_order = sorted(rows, key=lambda n: -PAPER_ABLATION[n][1])

    def measured(higher: str, lower: str) -> Difference:
        return difference(rows[higher], rows[lower])

    order = compare_order(paper_order, measured)
    n_pairs = len(rows) * (len(rows) - 1) // 2
    lines = [f"## Against the paper's order ({len(rows)} ablation rows, {n_pairs} pairs)", "",
             f"Of the {n_pairs} pairs the paper orders: {len(order.agree)} resolved in the paper's order, "
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


def machines_text(runs: list[Run]) -> str:
    seen = sorted({(r.results["machine"]["host"], r.results["machine"]["device"])
                   for r in runs if r.results and "machine" in r.results})
    where = "; ".join(f"{host}: {device}" for host, device in seen) or "unknown"
    note = (" Runs come from different machines, so their times are not comparable with each other."
            if len(seen) > 1 else "")
    return (f"Times are training wall-clock seconds as each run measured them (periodic validation included; "
            f"preparing the data and the final test not), on {where}.{note}")


def markdown(variants: list[Variant], runs: list[Run], sources: list[Path], reference: Variant | None = None) -> str:
    planned = [(source, planned_jobs(source)) for source in sources]
    started = {source: sum(source in run.path.parents for run in runs) for source in sources}
    not_started = [f"`{source}` plans {n} jobs, {started[source]} started" for source, n in planned
                   if n is not None and n > started[source]]
    rows = table_rows(variants, reference)
    order = ["finished", "failed", "killed", "running", "damaged", "unknown"]
    states = {state: n for state in order if (n := sum(run.state == state for run in runs))}
    has_paper = any(row["paper_row"] for row in rows)
    header = ["variant", "runs", "test PSNR (dB)", "test SSIM"]
    if reference is not None:
        header += ["PSNR - reference (95% CI)", "SSIM - reference (95% CI)", "verdict (PSNR)"]
    header += ["train time (s)", "s / step", "rays / s", "params", "evals / ray"]
    if has_paper:
        header += ["paper row", "paper PSNR", "paper SSIM", "PSNR - paper"]
    lines = [
        "# nerfexp report", "",
        f"Runs: {len(runs)} ({', '.join(f'{n} {s}' for s, n in states.items())}) from "
        f"{', '.join(f'`{s}`' for s in sources)}. Means ± sample standard deviation over each variant's "
        "finished runs. " + machines_text(runs), "", reference_text(reference), "",
        "| " + " | ".join(header) + " |", "|" + "---|" * len(header),
    ]
    for v, row in zip(variants, rows):
        cells = [row["variant"], f"{row['finished']}/{row['runs']}", _pm(v, "test_psnr", 2), _pm(v, "test_ssim", 3)]
        if reference is not None:
            if v is reference or not v.finished:
                cells += ["reference" if v is reference else "–"] * 3
            else:
                cells += [difference(v, reference, "test_psnr").describe(2),
                          difference(v, reference, "test_ssim").describe(3), row["verdict"]]
        cells += [_fmt(row["train_time_s"], 0), _fmt(row["time_per_step_s"], 4), _fmt(row["rays_per_s"], 0),
                 _fmt(row["n_params"], 0), _fmt(row["evaluations_per_ray"], 0)]
        if has_paper:
            cells += [row["paper_row"], _fmt(row["paper_psnr"], 2), _fmt(row["paper_ssim"], 3),
                      _fmt(row["psnr_minus_paper"], 2)]
        lines.append("| " + " | ".join(cells) + " |")
    if has_paper:
        lines += ["", "The paper's numbers are means over its 8 Realistic Synthetic scenes at 800 x 800; the "
                  "difference is given only for runs on Blender data."]
    lines += [""] + ranking_text(variants)
    unfinished = [run for run in runs if run.state != "finished"]
    lines += ["", "## Jobs that did not finish, or whose files are damaged (not counted)", ""]
    lines += [f"- `{run.path}` ({overrides_text(run.overrides)}): {run.state}"
              + (f": {run.detail}" if run.detail else "") for run in unfinished]
    lines += [f"- {text}: the rest never started (the sweep stopped or is still going)" for text in not_started]
    if not unfinished and not not_started:
        lines.append("None.")
    lines += ["", "Plots: `psnr_vs_time.png` (validation PSNR against training seconds: each variant's mean "
              "over seeds, its band from the lowest to the highest seed, single runs faint), `pareto.png` "
              "(test PSNR against total training time, bars one standard deviation over seeds)."]
    return "\n".join(lines) + "\n"


def overrides_text(overrides: list[str] | None) -> str:
    """A job's overrides as the report lists them."""
    if overrides is None:
        return "overrides unreadable"
    return ", ".join(overrides) or "no overrides"


def reference_text(reference: Variant | None) -> str:
    if reference is None:
        return ("No reference variant (the sweep has no `ablation=complete`; name one with `--reference "
                "VARIANT`), so no differences between variants are given beside the table.")
    return (f"Differences are to the reference, `{reference.label}`: the mean over seeds of (variant - reference), "
            "each run paired with the reference's run of the same seed, with its 95% confidence interval "
            "(Student's t, n - 1 degrees of freedom). Verdict: better or worse where the interval excludes "
            "zero, else not resolved with this many seeds; one seed gives no interval. Intervals are per "
            "comparison, not corrected for making many.")


def csv_text(variants: list[Variant], reference: Variant | None = None) -> str:
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(table_rows(variants, reference))
    return out.getvalue()


FIGSIZE, DPI = (8.0, 5.0), 100  # 800 x 500 pixels


LEGEND_INSIDE = 6  # entries; more go below the axes, the figure taller by a line's height (inches) for each
LEGEND_LINE = 0.2


def legend(figure: Figure, axes) -> None:
    """The plot's legend, if it has entries: inside the axes, or below them where so many entries would
    hide the data (a sweep's dozen variants)."""
    handles, labels = axes.get_legend_handles_labels()
    if len(handles) <= LEGEND_INSIDE:
        if handles:
            axes.legend(fontsize="small")
        return
    figure.set_figheight(FIGSIZE[1] + LEGEND_LINE * len(handles))
    figure.legend(handles, labels, loc="outside lower center", fontsize="small")


def _save(figure: Figure) -> bytes:
    out = io.BytesIO()
    figure.savefig(out, format="png", dpi=DPI)
    return out.getvalue()


def mean_curve(runs: list[Run]) -> list[tuple[float, float, float, float]]:
    """The runs' validation curves averaged at each step that every one of them reached: (mean seconds,
    mean PSNR, lowest PSNR, highest PSNR) per step, in step order."""
    by_step = [{step: (seconds, psnr) for step, seconds, psnr in run.curve} for run in runs]
    steps = sorted(set.intersection(*(set(curve) for curve in by_step))) if by_step else []
    points = []
    for step in steps:
        seconds, psnrs = zip(*(curve[step] for curve in by_step))
        points.append((statistics.fmean(seconds), statistics.fmean(psnrs), min(psnrs), max(psnrs)))
    return points


MARKERS = "o^sDvP"  # with 10 colours, 60 variants each drawn differently


def variant_style(i: int) -> tuple[str, str]:
    """The colour and marker of the ``i``-th variant in both plots: the 10 default colours, then the
    same colours with the next marker."""
    return f"C{i % 10}", MARKERS[i // 10 % len(MARKERS)]


def psnr_vs_time_png(variants: list[Variant]) -> bytes:
    """Validation PSNR against training seconds: a variant's mean over its finished runs (at the steps
    they all reached) with a band from the lowest to the highest run; every run faint in the same colour."""
    figure = Figure(figsize=FIGSIZE, layout="constrained")
    axes = figure.add_subplot()
    for i, variant in enumerate(variants):
        colour, marker = variant_style(i)
        for run in variant.runs:
            if run.curve:
                axes.plot(*zip(*[(t, p) for _, t, p in run.curve]), color=colour, linewidth=0.8, alpha=0.25)
        points = mean_curve([run for run in variant.finished if run.curve])
        if points:
            seconds, mean, low, high = zip(*points)
            axes.plot(seconds, mean, color=colour, marker=marker, markersize=4, linewidth=1.6,
                      label=f"{variant.label} ({seeds(len(variant.finished))})")
            if len(variant.finished) > 1:
                axes.fill_between(seconds, low, high, color=colour, alpha=0.15, linewidth=0)
    axes.set(xlabel="training wall-clock time (s)", ylabel="validation PSNR (dB)",
             title="Validation PSNR against training time\nline: mean over seeds; band: lowest to highest seed; "
                   "faint: single runs")
    axes.grid(alpha=0.3)
    legend(figure, axes)
    return _save(figure)


def pareto_png(variants: list[Variant]) -> bytes:
    """Mean test PSNR against mean training time (bars: one sample standard deviation over seeds, none
    for one seed), the Pareto front of the means dashed."""
    figure = Figure(figsize=FIGSIZE, layout="constrained")
    axes = figure.add_subplot()
    points = []
    for i, variant in enumerate(variants):
        if not variant.finished:
            continue
        x, y = variant.mean("train_time_s"), variant.mean("test_psnr")
        xerr, yerr = (0 if not math.isfinite(s) else s for s in (variant.std("train_time_s"), variant.std("test_psnr")))
        colour, marker = variant_style(i)
        axes.errorbar(x, y, xerr=xerr, yerr=yerr, fmt=marker, color=colour, label=variant.label, capsize=3)
        points.append((x, y))
    front, best = [], -math.inf
    for x, y in sorted(points, key=lambda p: (p[0], -p[1])):  # faster first; keep each new best PSNR
        if y > best:
            front.append((x, y))
            best = y
    if len(front) > 1:
        axes.plot(*zip(*front), "k--", linewidth=1, label="Pareto front")
    axes.set(xlabel="training wall-clock time (s)", ylabel="test PSNR (dB)",
             title="Final quality against total training time\npoints: means over seeds; bars: ± 1 sample "
                   "standard deviation over seeds")
    axes.grid(alpha=0.3)
    legend(figure, axes)
    return _save(figure)


IMAGES_DIR = "report_images"
VIEWS_SHOWN = 3  # test views on the page by default: the first, the middle and the last
PLOTS = [("psnr_vs_time.png", "validation PSNR against training seconds"),
         ("pareto.png", "test PSNR against total training time")]


def default_views(n_views: int, count: int = VIEWS_SHOWN) -> list[int]:
    """``count`` of ``n_views`` test views spread evenly from the first to the last (all where there are
    fewer). Example: 8 views, count 3: [0, 4, 7]."""
    if n_views <= 1:
        return list(range(n_views))
    shown = min(count, n_views)
    return sorted({round(k * (n_views - 1) / (shown - 1)) for k in range(shown)})


def run_seed(run: Run) -> int | None:
    seed = (run.results or {}).get("config", {}).get("seed")
    return seed if isinstance(seed, int) else None


def shown_run(variant: Variant) -> Run | None:
    """The variant's finished run whose renders the page shows: the one with the lowest seed, so that
    variants are shown with the same seed where they have it (then the first by path)."""
    return min(variant.finished, key=lambda run: (run_seed(run) is None, run_seed(run) or 0, str(run.path)),
               default=None)


ERROR_WHITE = 0.25  # the error heat map's scale: 0 black, this mean absolute error (of 1) and above white


def error_heatmap(rgba: Tensor) -> Tensor:
    """The heat map [H, W, 3] (uint8) of an error image [H, W, 4] (uint8, |render - truth| per channel as
    a run saves it): the mean over the colour channels on matplotlib's ``magma`` map, 0 black and
    ``ERROR_WHITE`` or more white, the same scale for every variant."""
    error = rgba[..., :3].double().mean(-1) / 255 / ERROR_WHITE
    return torch.from_numpy(colormaps["magma"](error.clamp(0, 1).numpy(), bytes=True)[..., :3])


def copy_picture(source: Path, folder: Path, name: str, alt: str,
                 pixels: Callable[[Tensor], Tensor] = lambda rgba: rgba[..., :3]) -> Picture:
    """The image file ``source`` (a run's render, read as data: decoded with its checks, never copied
    byte for byte) written anew as the RGB PNG ``folder/name`` of ``pixels(rgba)`` (uint8 [H, W, 4] ->
    [H, W, 3]); a missing or damaged file is a ``Picture`` saying so. ``name`` is relative to the page's
    folder."""
    try:
        rgba = read_image(source, "the run's test renders")
    except DatasetError as error:
        return Picture(alt, missing="missing" if not source.is_file() else f"unreadable: {error}")
    (folder / name).parent.mkdir(parents=True, exist_ok=True)
    (folder / name).write_bytes(png_bytes(pixels(rgba).numpy()))
    return Picture(alt, f"{IMAGES_DIR}/{name}", rgba.shape[1])


def view_tiles(variants: list[Variant], views: list[int], folder: Path) -> dict[int, list[Tile]]:
    """For each test view in ``views``: a ground-truth tile, then each variant's render and error image
    (``shown_run``) with that view's PSNR and SSIM; the pictures written into ``folder``."""
    shown = [(variant, shown_run(variant)) for variant in variants]
    tiles = {}
    for index in views:
        truth = next((path for _, run in shown
                      if run is not None and (path := run.path / "test" / f"r_{index}_target.png").is_file()), None)
        row = [Tile("ground truth", (copy_picture(truth, folder, f"view{index}/truth.png", "ground truth")
                                     if truth else Picture("ground truth", missing="missing"),))]
        for k, (variant, run) in enumerate(shown):
            if run is None:
                row.append(Tile(variant.label, (Picture("render", missing="no finished run"),)))
                continue
            test = run.path / "test"
            pictures = (copy_picture(test / f"r_{index}.png", folder, f"view{index}/{k}.png", "render"),
                        copy_picture(test / f"r_{index}_error.png", folder, f"view{index}/{k}_error.png",
                                     "error heat map", error_heatmap))
            caption = f"seed {run_seed(run)}"
            if index in (views_run := run.results.get("test_views", [])):
                at = views_run.index(index)
                psnr, ssim = (run.results.get(f"test_{m}_per_view", [math.nan] * len(views_run))[at]
                              for m in ("psnr", "ssim"))
                caption = f"PSNR {psnr:.2f} dB, SSIM {ssim:.3f}, {caption}"
            row.append(Tile(variant.label, pictures, caption))
        tiles[index] = row
    return tiles


def check_views(variants: list[Variant], views: list[int] | None) -> list[int]:
    """The test views to show: ``views`` where every one is a test view of some shown run, else a
    SystemExit naming the ones that are not; None: ``default_views`` of the runs' test views."""
    available = sorted({i for v in variants if (run := shown_run(v)) for i in run.results.get("test_views", [])})
    if views is None:
        return [available[i] for i in default_views(len(available))]
    if unknown := [i for i in views if i not in available]:
        have = f"views {available[0]} to {available[-1]}" if available else "no test views"
        raise SystemExit(f"nerfexp-report: error: --views {' '.join(map(str, unknown))}: not a test view of "
                         f"the runs shown (they have {have})")
    return list(dict.fromkeys(views))


VIEWS_NOTE = ("Each variant's run with the lowest seed: its render of the view (top) and its error (below): "
              "the absolute difference to the ground truth averaged over the colour channels, black 0, white "
              f"{ERROR_WHITE:g} and above (magma). The PSNR and SSIM are that run's on that view. Small images "
              "are enlarged with visible pixels.")


def check_out(out: Path) -> None:
    """A NerfexpError where the report's folder ``out`` holds files that neither a report (``REPORT_MADE``)
    nor a sweep (``SWEEP_MADE``) made, outside the run directories in it (``find_run_dirs``; where ``out``
    is one, those its commands make, ``RUN_MADE``, and its log): a report writes over nothing a user made."""
    runs = {run.relative_to(out) for run in find_run_dirs(out)}
    made = (*REPORT_MADE, *SWEEP_MADE, *TEMPORARY, *((*RUN_MADE, "*.log") if Path(".") in runs else ()))
    foreign = [entry for entry in folder_entries(out)
               if not is_made(entry, made) and not runs & (set(Path(entry).parents) - {Path(".")})]
    if foreign:
        raise NerfexpError(foreign_message(out, foreign, "nerfexp-report",
                                           "choose another folder for the report (--out DIR)"))


def write_report(directories: list[Path], out: Path, over: tuple[str, ...] = ("seed",),
                 reference: str | None = None, views: list[int] | None = None) -> list[Variant]:
    """The report of the runs under ``directories`` in ``out``; ``reference``: the variant the others are
    compared with (see ``reference_variant``); ``views``: the test views on the page (``check_views``);
    ``out`` is checked first (``check_out``)."""
    check_out(out)
    runs = find_runs(directories)
    variants = group_variants([run for run in runs if run.overrides is not None], over)
    base = reference_variant(variants, reference)
    views = check_views(variants, views)
    report_md = markdown(variants, runs, directories, base)
    atomic_write(out / "report.md", report_md.encode())
    atomic_write(out / "report.csv", csv_text(variants, base).encode())
    atomic_write(out / "psnr_vs_time.png", psnr_vs_time_png(variants))
    atomic_write(out / "pareto.png", pareto_png(variants))
    with atomic_directory(out / IMAGES_DIR, replace=True) as folder:
        tiles = view_tiles(variants, views, folder)
    atomic_write(out / "report.html", page_html(report_md, PLOTS, tiles, VIEWS_NOTE).encode())
    return variants


def build_parser() -> argparse.ArgumentParser:
    """The ``nerfexp-report`` command line (the module's first paragraph describes it)."""
    parser = command_parser("nerfexp-report", __doc__.split("\n\n")[0])
    parser.add_argument("dirs", nargs="+", type=Path, help="multirun or run directories")
    parser.add_argument("--out", type=Path, help="where to write the report (default: the first directory)")
    parser.add_argument("--over", nargs="+", default=["seed"],
                        help="override keys averaged over within a variant (default: seed)")
    parser.add_argument("--reference", metavar="VARIANT",
                        help="the variant the others are compared with, by its label in the report (e.g. "
                             "'encoding=posenc, hierarchical=true'); default: ablation=complete if in the sweep")
    parser.add_argument("--views", nargs="+", type=int, metavar="INDEX",
                        help="test views shown in report.html, each variant's render beside the ground truth "
                             f"(default: {VIEWS_SHOWN} spread from the first to the last)")
    return parser


def main(argv: list[str] | None = None) -> None:
    """The ``nerfexp-report`` command (``build_parser``)."""
    args = build_parser().parse_args(argv)
    out = args.out or args.dirs[0]
    with one_line_errors("nerfexp-report"):
        variants = write_report(args.dirs, out, tuple(args.over), args.reference, args.views)
    print(f"{len(variants)} variants; report in {out / 'report.md'} and {out / 'report.html'}", file=sys.stderr)
