"""Error against cost for the renderer: analytic fields rendered with stratified and hierarchical sampling.

For each field of ``tests/analytic.py`` (a slab, a thin shell, a Gaussian blob), a batch of rays aimed so
that its surfaces fall everywhere relative to the sample grid is rendered by ``VolumeRenderer`` with
deterministic (test-time) sampling in float32, as in training, by:

- ``stratified``: N samples per ray, N = 4 ... 2048;
- ``hierarchical 1:3``: N / 4 coarse and 3 N / 4 fine samples (1.25 N network evaluations per ray);
- ``hierarchical, 16 coarse`` and ``hierarchical, 64 coarse``: a fixed coarse pass, growing fine samples.

Each is scored against the float64 truth (``tests.analytic.render_errors``: mean absolute opacity and
colour error, opacity-weighted mean absolute depth error) and timed: the wall time to render the batch,
the median of ``--repeats`` repeats, every configuration once per repeat in a shuffled order, so that
machine load affects all alike (torch threads as the machine sets them). Writes
``benchmarks/results/quadrature.json``, ``.md`` (tables) and ``.png`` (error against wall time and
against network evaluations per ray, log-log, one line per method).

    python -m benchmarks.accuracy.quadrature [--rays 2048] [--repeats 7]   # from the repository root
                                                                            # (it imports tests.analytic)
"""

import argparse
import io
import json
import os
import random
import statistics
import time
from pathlib import Path

import torch
from matplotlib.figure import Figure
from tests.analytic import GaussianBlob, Shell, Slab, aimed_rays, cost_for_error, render_errors

from nerfexp.files import atomic_write
from nerfexp.nerf.backgrounds import BACKGROUNDS
from nerfexp.nerf.hierarchy import HierarchyChoice
from nerfexp.nerf.volume_renderer import VolumeRenderer, final_output
from nerfexp.rundir.layout import machine

RESULTS = Path(__file__).parents[1] / "results"  # benchmarks/results
NEAR, FAR, BACKGROUND = 2.0, 6.0, "white"
FIELDS = {  # name: (field, how rays are aimed at it: see tests.analytic.aimed_rays)
    "slab": (Slab(), dict(impact=0.0, distance=(3.5, 4.5), cone_degrees=60.0)),  # |z| < 0.5, density 3
    "shell": (Shell(), dict(impact=1.1, distance=(3.5, 4.5))),  # radius 1, 0.1 thick, density 10
    "blob": (GaussianBlob(), dict(impact=0.6, distance=(3.5, 4.5))),  # r = 0.3, peak density 5
}
DOUBLINGS = [2**k for k in range(2, 12)]  # 4 ... 2048
METHODS = {  # name: [(n_coarse, n_fine)]; n_fine = 0 is stratified with n_coarse samples
    "stratified": [(n, 0) for n in DOUBLINGS],
    "hierarchical 1:3": [(n // 4, n - n // 4) for n in DOUBLINGS[2:]],  # from 4 + 12
    "hierarchical, 16 coarse": [(16, n) for n in DOUBLINGS[1:]],
    "hierarchical, 64 coarse": [(64, n) for n in DOUBLINGS[2:]],
}
TARGETS = (1e-2, 1e-3)


def renderer(field, n_coarse: int, n_fine: int) -> VolumeRenderer:
    hierarchical = n_fine > 0
    return VolumeRenderer(lambda: field, HierarchyChoice(hierarchical, n_coarse, n_fine, n_coarse), NEAR, FAR,
                          BACKGROUND)


def render(model: VolumeRenderer, origins, directions) -> tuple[dict, float]:
    """The final output for rays [B, 3] and the wall time to render them, in seconds."""
    start = time.perf_counter()
    with torch.no_grad():
        out = model(origins, directions, deterministic=True)
    seconds = time.perf_counter() - start
    return final_output(out), seconds


def measure(n_rays: int, repeats: int) -> list[dict]:
    """One row per field, method and sample count: errors, evaluations per ray, median render time."""
    jobs = []
    for name, (field, aim) in FIELDS.items():
        origins, directions = aimed_rays(n_rays, torch.Generator().manual_seed(0), **aim)
        truth = field.truth(origins, directions, NEAR, FAR, BACKGROUNDS[BACKGROUND])
        rays = origins.float(), directions.float()
        for method, counts in METHODS.items():
            for n_coarse, n_fine in counts:
                model = renderer(field, n_coarse, n_fine)
                out, _ = render(model, *rays)  # deterministic: the errors once; also a warm-up
                jobs.append(dict(field=name, method=method, n_coarse=n_coarse, n_fine=n_fine,
                                 evaluations_per_ray=model.evaluations_per_ray,
                                 **{f"{k}_error": v for k, v in render_errors(out, truth).items()},
                                 seconds=[], model=model, rays=rays))
    for repeat in range(repeats):
        for job in random.Random(repeat).sample(jobs, len(jobs)):
            job["seconds"].append(render(job["model"], *job["rays"])[1])
        print(f"repeat {repeat + 1}/{repeats} done", flush=True)
    for job in jobs:
        del job["model"], job["rays"]
        job["time_ms"], job["time_ms_min"] = 1000 * statistics.median(job["seconds"]), 1000 * min(job["seconds"])
        job["seconds"] = [round(s, 5) for s in job["seconds"]]
    return jobs


def curves(rows: list[dict]) -> dict[tuple[str, str], list[dict]]:
    """Rows grouped by (field, method), in increasing evaluations per ray."""
    grouped: dict[tuple[str, str], list[dict]] = {}
    for row in rows:
        grouped.setdefault((row["field"], row["method"]), []).append(row)
    return {key: sorted(group, key=lambda r: r["evaluations_per_ray"]) for key, group in grouped.items()}


def needed(group: list[dict], quantity: str, target: float) -> str:
    """'evaluations (ms)' at which the error of ``quantity`` gets below ``target`` (log-log interpolated)."""
    errors = [r[f"{quantity}_error"] for r in group]
    evaluations = cost_for_error(target, [r["evaluations_per_ray"] for r in group], errors)
    if evaluations is None:
        return f"> {group[-1]['evaluations_per_ray']}"
    milliseconds = cost_for_error(target, [r["time_ms"] for r in group], errors)
    at_most = "<= " if evaluations == group[0]["evaluations_per_ray"] else ""
    return f"{at_most}{evaluations:.0f} ({milliseconds:.0f} ms)"


def per_evaluation(rows: list[dict], hierarchical: bool) -> float:
    """Median milliseconds per network evaluation per ray, over the runs with at least 256 evaluations."""
    return statistics.median(r["time_ms"] / r["evaluations_per_ray"] for r in rows
                             if (r["n_fine"] > 0) == hierarchical and r["evaluations_per_ray"] >= 256)


def markdown(report: dict) -> str:
    rows, settings = report["rows"], report["settings"]
    grouped = curves(rows)
    lines = [
        "# Quadrature error against cost",
        "",
        f"`python -m benchmarks.accuracy.quadrature`: {settings['rays']} rays per field, deterministic sampling, "
        f"float32, near {NEAR}, far {FAR}, {BACKGROUND} background; times are the median of {settings['repeats']} "
        f"renders of the whole batch. Machine: {report['machine']['device']} on {report['machine']['host']}, torch "
        f"{report['torch']}; load average {report['load_average']['start']} at the start, "
        f"{report['load_average']['end']} at the end.",
        "",
        "Methods: `stratified` N samples; `hierarchical 1:3` N / 4 coarse then 3 N / 4 fine samples "
        "(1.25 N network evaluations per ray); `hierarchical, 16 coarse` and `64 coarse`: a fixed coarse "
        "pass and growing fine samples. Network evaluations per ray (and the batch's median render time) "
        "for a mean error below each target, interpolated in log-log between the measured points "
        "(`<= N`: already below at the cheapest point measured; `> N`: not reached up to N):",
        "",
        "| field | method | opacity < 1e-2 | opacity < 1e-3 | depth < 1e-2 | depth < 1e-3 |",
        "|---|---|---|---|---|---|",
    ]
    for (field, method), group in grouped.items():
        cells = [needed(group, quantity, target) for quantity in ("opacity", "depth") for target in TARGETS]
        lines.append(f"| {field} | {method} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Opacity and colour errors are means over rays (and channels) of absolute errors; the depth error is "
        "weighted by each ray's true opacity. Each field has one colour c, so its colour error is "
        "|c - background| times the opacity error. Network evaluations per ray are the samples per ray: N "
        "stratified, n_coarse + (n_coarse + n_fine) hierarchical. The render times are the renderer's own "
        "work (sampling, sorting, compositing), as the analytic fields cost almost nothing to evaluate: "
        f"here a network evaluation costs {per_evaluation(rows, True) / per_evaluation(rows, False):.1f} times "
        "as long with hierarchical sampling as without; with a NeRF MLP, whose evaluations dominate, time "
        "follows evaluations. The blob's stratified opacity error stops near 1e-7: float32 rounding.",
        "",
        "| field | method | coarse | fine | evaluations / ray | opacity error | depth error | colour error "
        "| median ms |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for (field, method), group in grouped.items():
        for r in group:
            lines.append(f"| {field} | {method} | {r['n_coarse']} | {r['n_fine']} | {r['evaluations_per_ray']} | "
                         f"{r['opacity_error']:.2e} | {r['depth_error']:.2e} | {r['rgb_error']:.2e} | "
                         f"{r['time_ms']:.1f} |")
    return "\n".join(lines) + "\n"


def png(report: dict) -> bytes:
    """For each field (a row): opacity and depth error against wall time and against evaluations per ray."""
    grouped = curves(report["rows"])
    figure = Figure(figsize=(16, 11), layout="constrained")
    panels = figure.subplots(len(FIELDS), 4)
    columns = [("opacity", "time_ms", "render time of the batch (ms)"),
               ("opacity", "evaluations_per_ray", "network evaluations per ray"),
               ("depth", "time_ms", "render time of the batch (ms)"),
               ("depth", "evaluations_per_ray", "network evaluations per ray")]
    for row, field in enumerate(FIELDS):
        for column, (quantity, x_key, x_label) in enumerate(columns):
            axes = panels[row, column]
            for i, method in enumerate(METHODS):
                group = grouped[field, method]
                axes.loglog([r[x_key] for r in group], [r[f"{quantity}_error"] for r in group], marker="o",
                            markersize=3, color=f"C{i}", label=method)
            for target in TARGETS:
                axes.axhline(target, color="grey", linestyle=":", linewidth=0.8)
            against = "time" if x_key == "time_ms" else "evaluations"
            axes.set(xlabel=x_label, ylabel=f"{quantity} error", title=f"{field}: {quantity} error against {against}")
            axes.grid(alpha=0.3, which="both", linewidth=0.5)
    panels[0, 0].legend(fontsize="small")
    figure.suptitle(f"Volume-rendering quadrature: mean error against cost, {report['settings']['rays']} rays "
                    f"per field, deterministic sampling, float32 ({report['machine']['device']})")
    out = io.BytesIO()
    figure.savefig(out, format="png", dpi=80)
    return out.getvalue()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rays", type=int, default=2048)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    load_start = os.getloadavg()
    rows = measure(args.rays, args.repeats)
    report = {"machine": machine(), "torch": torch.__version__,
              "load_average": {"start": [round(x, 2) for x in load_start],
                               "end": [round(x, 2) for x in os.getloadavg()]},
              "settings": {"rays": args.rays, "repeats": args.repeats, "near": NEAR, "far": FAR,
                           "background": BACKGROUND, "dtype": "float32", "deterministic": True},
              "rows": rows}
    atomic_write(RESULTS / "quadrature.json", (json.dumps(report, indent=1) + "\n").encode())
    text = markdown(report)
    atomic_write(RESULTS / "quadrature.md", text.encode())
    atomic_write(RESULTS / "quadrature.png", png(report))
    print(text)


if __name__ == "__main__":
    main()
