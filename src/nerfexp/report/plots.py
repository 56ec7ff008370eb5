"""The report's plots: validation PSNR against training time, the Pareto plot of final quality (and each
budget's) against training time, and each variant's test PSNR difference to the reference against training time."""


import io
import math
import statistics

from matplotlib.figure import Figure

from nerfexp.report.budgets import budget_points, difference_curve
from nerfexp.report.comparison import SEED, seeds
from nerfexp.report.runs import Run
from nerfexp.report.shared_machines import timed_labels
from nerfexp.report.variants import Variant

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


def runs_text(variant: Variant) -> str:
    """A variant's finished runs in its legend: "3 seeds"; over more than the seed (a sweep over scenes), "8 runs"."""
    return seeds(len(variant.finished), SEED if variant.paired_by == SEED else "run")


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
                      label=f"{variant.label} ({runs_text(variant)})")
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
    for one seed), the Pareto front of the means dashed; a variant's earlier budgets (``budget_points``: mean time
    and test PSNR of its runs at each step they share) as small points joined to its end by a thin line."""
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
        budgets = budget_points(variant)
        if len(budgets) > 1:
            _, times, psnrs = zip(*budgets)
            axes.plot(times, psnrs, color=colour, marker=marker, markersize=3, linewidth=0.7, alpha=0.6)
    front, best = [], -math.inf
    for x, y in sorted(points, key=lambda p: (p[0], -p[1])):  # faster first; keep each new best PSNR
        if y > best:
            front.append((x, y))
            best = y
    if len(front) > 1:
        axes.plot(*zip(*front), "k--", linewidth=1, label="Pareto front")
    axes.set(xlabel="training wall-clock time (s)", ylabel="test PSNR (dB)",
             title="Quality against training time\npoints: means over seeds; bars: ± 1 sample standard "
                   "deviation over seeds\nsmall points on a thin line: the variant's test budgets on the way")
    axes.grid(alpha=0.3)
    legend(figure, axes)
    return _save(figure)


def difference_vs_time_png(variants: list[Variant], reference: Variant | None) -> bytes:
    """Each variant's test PSNR - the reference's against training time, paired by seed at the matched times
    (``difference_curve``: each run's score interpolated between its budgets, where every run of both has one), the
    mean a line and its 95% interval a band, zero a black line; only variants whose times, and the reference's,
    may be compared (``timed_labels``). A plot without curves says why in its title."""
    figure = Figure(figsize=FIGSIZE, layout="constrained")
    axes = figure.add_subplot()
    drawn, timed = False, timed_labels(variants)
    for i, variant in enumerate(variants):
        if reference is None or variant is reference or not {variant.label, reference.label} <= timed:
            continue
        curve = [(t, d) for t, d in difference_curve(variant, reference) if d.n > 0]
        if not curve:
            continue
        colour, marker = variant_style(i)
        times = [t for t, _ in curve]
        axes.plot(times, [d.mean for _, d in curve], color=colour, linewidth=1.6, marker=marker, markevery=[-1],
                  markersize=4, label=f"{variant.label} ({seeds(max(d.n for _, d in curve), curve[0][1].unit)})")
        band = [(t, *d.interval) for t, d in curve if d.interval is not None]
        if band:
            axes.fill_between(*zip(*band), color=colour, alpha=0.15, linewidth=0)
        drawn = True
    axes.axhline(0.0, color="k", linewidth=0.8)
    if drawn:
        title = (f"Test PSNR - reference ({reference.label}) against training time\nline: mean of the differences "
                 "paired by seed; band: its 95% interval")
    elif reference is None:
        title = "No difference against time: the report has no reference variant"
    else:
        title = ("No difference against time: no variant's runs and the reference's share a training time\n"
                 "(or their runs' times may not be compared: report.md's note on times)")
    axes.set(xlabel="training wall-clock time (s)", ylabel="test PSNR difference (dB)", title=title)
    axes.grid(alpha=0.3)
    legend(figure, axes)
    return _save(figure)
