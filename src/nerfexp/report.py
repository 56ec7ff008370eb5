"""``nerfexp-report``: a sweep's variants side by side, their quality against the compute they cost.

Reads every run under the given directories (a run is a folder holding ``status.json`` or
``results.json``, as ``nerfexp`` writes them), groups runs into variants and writes

- ``report.md`` / ``report.csv``: one row per variant: test PSNR and SSIM (mean and sample standard
  deviation over the runs of the variant, usually its seeds), training time, time per step, rays/s,
  parameters, network evaluations per ray, and for rows of the paper's ablation table the paper's
  numbers beside ours; then the ranking and whether it agrees with the paper's; then every job that
  did not finish (failed, or running / killed) with its reason;
- ``psnr_vs_time.png``: validation PSNR against training wall-clock seconds, one colour per variant;
- ``pareto.png``: final test PSNR against total training time, the Pareto front drawn through it.

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
from dataclasses import dataclass, field
from itertools import combinations
from pathlib import Path

from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.override_parser.overrides_parser import OverridesParser
from matplotlib.figure import Figure
from omegaconf import OmegaConf

from nerfexp.files import atomic_write
from nerfexp.rundir import RESULTS, STATUS, find_run_dirs, process_alive, read_json, read_metrics

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
    overrides: list[str]
    detail: str = ""
    results: dict | None = None
    curve: list[tuple[float, float]] = field(default_factory=list)  # (wall seconds, validation PSNR)


@dataclass
class Variant:
    label: str
    runs: list[Run]

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

    def choice(self, key: str):
        """The variant's choice of a config group, where all its finished runs agree."""
        values = {run.results["choices"].get(key) for run in self.finished}
        return values.pop() if len(values) == 1 else None

    @property
    def paper(self) -> tuple[str, float, float] | None:
        return PAPER_ABLATION.get(self.choice("ablation"))


def read_run(path: Path) -> Run:
    """What a run directory says about its job. A job whose status still says running but whose
    process is gone from this host was killed (out of memory, a time limit, a signal)."""
    status = read_json(path / STATUS) or {}
    results = read_json(path / RESULTS)
    overrides = status.get("overrides", (results or {}).get("overrides", []))
    curve = [(record["wall_time_s"], record["psnr"]) for record in read_metrics(path) if record["split"] == "val"]
    state = status.get("state", "finished" if results is not None else "unknown")
    detail = status.get("error", "")
    if state == "finished" and results is None:
        state, detail = "failed", f"status says finished but {RESULTS} is missing"
    if state == "running":
        here = status.get("host") == socket.gethostname()
        if here and not process_alive(status["pid"], status.get("process_start")):
            state, detail = "killed", f"process {status['pid']} is gone (killed before it finished)"
        else:
            detail = f"on {status.get('host')}, process {status.get('pid')}" + ("" if here else " (not checked)")
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


def planned_jobs(directory: Path) -> int | None:
    """How many jobs the multirun in ``directory`` launches (its ``multirun.yaml``): the grid of a
    basic sweep, the trials of a search; None where that cannot be told."""
    path = directory / "multirun.yaml"
    if not path.exists():
        return None
    hydra = OmegaConf.load(path).hydra
    sweeper = hydra.sweeper
    if sweeper._target_.endswith("BasicSweeper"):
        params = [f"{key}={value}" for key, value in (sweeper.params or {}).items()] + list(hydra.overrides.task)
        batches = BasicSweeper.split_arguments(OverridesParser.create().parse_overrides(params), None)
        return sum(len(batch) for batch in batches)
    return sweeper.get("n_trials")


def _key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("+~")


def group_variants(runs: list[Run], over: tuple[str, ...] = ("seed",)) -> list[Variant]:
    """Runs with the same overrides, apart from the keys in ``over``, form a variant. Overrides that
    every run shares are left out of the labels. Variants are ranked by mean test PSNR."""
    kept = [tuple(o for o in run.overrides if _key(o) not in over) for run in runs]
    shared = set.intersection(*(set(k) for k in kept)) if kept else set()
    groups: dict[frozenset, tuple[tuple, list[Run]]] = {}  # the order of overrides does not matter
    for key, run in zip(kept, runs):
        groups.setdefault(frozenset(key), (key, []))[1].append(run)
    variants = []
    for key, members in groups.values():
        label = ", ".join(o for o in key if o not in shared) or ", ".join(key) or "default"
        variants.append(Variant(label, members))
    return sorted(variants, key=lambda v: (-v.mean("test_psnr") if v.finished else math.inf, v.label))


def kendall_tau(ours: list[str], theirs: list[str]) -> tuple[float, list[tuple[str, str]]]:
    """Kendall's rank correlation of two orderings of the same items, and the pairs they order
    differently (each as (ranked higher by us, ranked higher by them))."""
    position = {item: i for i, item in enumerate(theirs)}
    discordant = [(a, b) for a, b in combinations(ours, 2) if position[a] > position[b]]
    pairs = len(ours) * (len(ours) - 1) // 2
    return (1 - 2 * len(discordant) / pairs if pairs else 1.0), discordant


def _fmt(value: float, digits: int) -> str:
    return "–" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def _pm(variant: Variant, key: str, digits: int) -> str:
    mean, std = variant.mean(key), variant.std(key)
    return _fmt(mean, digits) + ("" if not math.isfinite(std) else f" ± {std:.{digits}f}")


COLUMNS = ("variant", "runs", "finished", "test_psnr_mean", "test_psnr_std", "test_ssim_mean", "test_ssim_std",
           "train_time_s", "time_per_step_s", "rays_per_s", "n_params", "evaluations_per_ray",
           "paper_row", "paper_psnr", "paper_ssim", "psnr_minus_paper")


def table_rows(variants: list[Variant]) -> list[dict]:
    """One dict per variant with the ``COLUMNS``; the difference to the paper only on Blender data
    (the paper's numbers are means over its 8 Blender scenes; other scenes are not comparable)."""
    rows = []
    for v in variants:
        paper = v.paper
        row = {"variant": v.label, "runs": len(v.runs), "finished": len(v.finished),
               "test_psnr_mean": v.mean("test_psnr"), "test_psnr_std": v.std("test_psnr"),
               "test_ssim_mean": v.mean("test_ssim"), "test_ssim_std": v.std("test_ssim"),
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
    ranked = [v for v in variants if v.finished]
    lines = ["## Ranking by mean test PSNR", ""]
    lines += [f"{i}. {v.label}: {v.mean('test_psnr'):.2f} dB" for i, v in enumerate(ranked, 1)]
    rows = [v for v in ranked if v.paper]
    names = [v.choice("ablation") for v in rows]
    lines.append("")
    if len(rows) < 2 or len(set(names)) != len(names):
        lines.append("No comparison with the paper's ordering: it needs at least two finished variants "
                     "that are distinct rows of the paper's ablation table (`ablation=...`).")
        return lines
    paper_order = sorted(names, key=lambda n: -PAPER_ABLATION[n][1])
    tau, discordant = kendall_tau(names, paper_order)
    if not discordant:
        lines.append(f"The ordering of these {len(names)} ablation rows agrees with the paper's Table 4.")
    else:
        lines.append(f"The ordering of these {len(names)} ablation rows differs from the paper's Table 4 "
                     f"in {len(discordant)} of {len(names) * (len(names) - 1) // 2} pairs "
                     f"(Kendall's tau {tau:.2f}):")
        lines += [f"- we rank {PAPER_ABLATION[a][0]} above {PAPER_ABLATION[b][0]}; the paper the reverse"
                  for a, b in discordant]
    return lines


def machines_text(runs: list[Run]) -> str:
    seen = sorted({(r.results["machine"]["host"], r.results["machine"]["device"])
                   for r in runs if r.results and "machine" in r.results})
    where = "; ".join(f"{host}: {device}" for host, device in seen) or "unknown"
    note = (" Runs come from different machines, so their times are not comparable with each other."
            if len(seen) > 1 else "")
    return (f"Times are training wall-clock seconds as each run measured them (periodic validation included; "
            f"preparing the data and the final test not), on {where}.{note}")


def markdown(variants: list[Variant], runs: list[Run], sources: list[Path]) -> str:
    planned = [(source, planned_jobs(source)) for source in sources]
    started = {source: sum(source in run.path.parents for run in runs) for source in sources}
    not_started = [f"`{source}` plans {n} jobs, {started[source]} started" for source, n in planned
                   if n is not None and n > started[source]]
    rows = table_rows(variants)
    order = ["finished", "failed", "killed", "running", "unknown"]
    states = {state: n for state in order if (n := sum(run.state == state for run in runs))}
    has_paper = any(row["paper_row"] for row in rows)
    header = ["variant", "runs", "test PSNR (dB)", "test SSIM", "train time (s)", "s / step", "rays / s",
              "params", "evals / ray"]
    if has_paper:
        header += ["paper row", "paper PSNR", "paper SSIM", "PSNR - paper"]
    lines = [
        "# nerfexp report", "",
        f"Runs: {len(runs)} ({', '.join(f'{n} {s}' for s, n in states.items())}) from "
        f"{', '.join(f'`{s}`' for s in sources)}. Means ± sample standard deviation over each variant's "
        "finished runs. " + machines_text(runs), "",
        "| " + " | ".join(header) + " |", "|" + "---|" * len(header),
    ]
    for v, row in zip(variants, rows):
        cells = [row["variant"], f"{row['finished']}/{row['runs']}", _pm(v, "test_psnr", 2), _pm(v, "test_ssim", 3),
                 _fmt(row["train_time_s"], 0), _fmt(row["time_per_step_s"], 4), _fmt(row["rays_per_s"], 0),
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
    lines += ["", "## Jobs that did not finish", ""]
    lines += [f"- `{run.path}` ({', '.join(run.overrides) or 'no overrides'}): {run.state}"
              + (f": {run.detail}" if run.detail else "") for run in unfinished]
    lines += [f"- {text}: the rest never started (the sweep stopped or is still going)" for text in not_started]
    if not unfinished and not not_started:
        lines.append("None.")
    lines += ["", "Plots: `psnr_vs_time.png` (validation PSNR against training seconds), `pareto.png` "
              "(test PSNR against total training time)."]
    return "\n".join(lines) + "\n"


def csv_text(variants: list[Variant]) -> str:
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(table_rows(variants))
    return out.getvalue()


FIGSIZE, DPI = (8.0, 5.0), 100  # 800 x 500 pixels


def _save(figure: Figure) -> bytes:
    out = io.BytesIO()
    figure.savefig(out, format="png", dpi=DPI)
    return out.getvalue()


def psnr_vs_time_png(variants: list[Variant]) -> bytes:
    """Validation PSNR against training seconds: each run a thin line, a variant's colour shared."""
    figure = Figure(figsize=FIGSIZE, layout="constrained")
    axes = figure.add_subplot()
    for i, variant in enumerate(variants):
        colour = f"C{i % 10}"
        for j, run in enumerate(r for r in variant.runs if r.curve):
            seconds, psnrs = zip(*run.curve)
            axes.plot(seconds, psnrs, color=colour, marker=".", linewidth=1.2, alpha=0.8,
                      label=variant.label if j == 0 else None)
    axes.set(xlabel="training wall-clock time (s)", ylabel="validation PSNR (dB)",
             title="Quality against run time (one line per run)")
    axes.grid(alpha=0.3)
    if axes.get_legend_handles_labels()[0]:
        axes.legend(fontsize="small")
    return _save(figure)


def pareto_png(variants: list[Variant]) -> bytes:
    """Mean test PSNR against mean training time (bars: standard deviation), Pareto front dashed."""
    figure = Figure(figsize=FIGSIZE, layout="constrained")
    axes = figure.add_subplot()
    points = []
    for i, variant in enumerate(variants):
        if not variant.finished:
            continue
        x, y = variant.mean("train_time_s"), variant.mean("test_psnr")
        xerr, yerr = (0 if not math.isfinite(s) else s for s in (variant.std("train_time_s"), variant.std("test_psnr")))
        axes.errorbar(x, y, xerr=xerr, yerr=yerr, fmt="o", color=f"C{i % 10}", label=variant.label, capsize=3)
        points.append((x, y))
    front, best = [], -math.inf
    for x, y in sorted(points, key=lambda p: (p[0], -p[1])):  # faster first; keep each new best PSNR
        if y > best:
            front.append((x, y))
            best = y
    if len(front) > 1:
        axes.plot(*zip(*front), "k--", linewidth=1, label="Pareto front")
    axes.set(xlabel="training wall-clock time (s)", ylabel="test PSNR (dB)",
             title="Final quality against total training time")
    axes.grid(alpha=0.3)
    if points:
        axes.legend(fontsize="small")
    return _save(figure)


def write_report(directories: list[Path], out: Path, over: tuple[str, ...] = ("seed",)) -> list[Variant]:
    runs = find_runs(directories)
    variants = group_variants(runs, over)
    atomic_write(out / "report.md", markdown(variants, runs, directories).encode())
    atomic_write(out / "report.csv", csv_text(variants).encode())
    atomic_write(out / "psnr_vs_time.png", psnr_vs_time_png(variants))
    atomic_write(out / "pareto.png", pareto_png(variants))
    return variants


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="nerfexp-report", description=__doc__.split("\n\n")[0])
    parser.add_argument("dirs", nargs="+", type=Path, help="multirun or run directories")
    parser.add_argument("--out", type=Path, help="where to write the report (default: the first directory)")
    parser.add_argument("--over", nargs="+", default=["seed"],
                        help="override keys averaged over within a variant (default: seed)")
    args = parser.parse_args(argv)
    out = args.out or args.dirs[0]
    variants = write_report(args.dirs, out, tuple(args.over))
    print(f"{len(variants)} variants; report in {out / 'report.md'}", file=sys.stderr)
