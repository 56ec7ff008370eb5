"""The report's folder: what it may already hold (``check_out``: of the files the report writes over,
none a user made), and every file of the report written into it (``write_report``; what they are: the
package's docstring), all at once and recorded in the folder's manifest as they are (``nerfexp.manifest``)."""


from collections.abc import Callable
from pathlib import Path

from nerfexp import manifest
from nerfexp.report.budget_tables import budget_rows, budgets_csv_text
from nerfexp.report.lpips_weights import vouched_lpips
from nerfexp.report.page import page_html
from nerfexp.report.pictures import PLOTS, VIEWS_NOTE, check_views, view_tiles
from nerfexp.report.plots import difference_vs_time_png, pareto_png, psnr_vs_time_png
from nerfexp.report.protocols import compared_runs
from nerfexp.report.runs import find_runs
from nerfexp.report.tables import csv_cell, csv_text, markdown, states_text, table_rows
from nerfexp.report.variants import Variant, group_variants, reference_variant
from nerfexp.rundir.layout import (
    DIFFERENCE_PLOT,
    PARETO_PLOT,
    PSNR_PLOT,
    REPORT_BUDGETS_CSV,
    REPORT_CSV,
    REPORT_FILES,
    REPORT_HTML,
    REPORT_IMAGES,
    REPORT_MD,
)


def check_out(out: Path) -> None:
    """A NerfexpError where a file the report writes over in ``out`` (``REPORT_FILES``, and every file under
    ``REPORT_IMAGES``, which is replaced as a whole) is not one a report wrote, by the folder's manifest
    (``nerfexp.manifest.check_ours``): a report writes over nothing a user made, and beside anything else."""
    manifest.check_ours(out, [*REPORT_FILES, *manifest.folder_files(out, REPORT_IMAGES)], "nerfexp-report",
                        "move {it}, or choose another folder for the report (--out DIR)")


def write_report(directories: list[Path], out: Path, over: tuple[str, ...] = ("seed",),
                 reference: str | None = None, views: list[int] | None = None,
                 progress: Callable[[str], None] = lambda line: None) -> list[Variant]:
    """The report of the runs under ``directories`` in ``out``; ``reference``: the variant the others are
    compared with (see ``reference_variant``); ``views``: the test views on the page (``check_views``);
    ``out`` is checked first (``check_out``). ``progress`` is told each step of the work in a line, as it begins.

    The report is written whole or not at all: each file and the pictures' folder is written beside its place
    first, and all are moved into place and recorded in the folder's manifest together at the end
    (``nerfexp.manifest.written_together``), so that a report stopped at any moment leaves the previous one as it
    was, and never a page naming pictures that are not there."""
    check_out(out)
    progress(f"reading the runs under {', '.join(map(str, directories))}")
    runs, protocols = compared_runs(find_runs(directories))  # the scores compared: of one protocol
    runs, weights = vouched_lpips(runs)  # LPIPS only of the published weights
    variants = group_variants([run for run in runs if run.overrides is not None], over)
    base = reference_variant(variants, reference)
    views = check_views(variants, views)
    budgets = sum(len(run.budgets) for variant in variants for run in variant.finished)
    progress(f"comparing {len(variants)} variants; runs: {states_text(runs)}; {budgets:,} test budgets")
    with manifest.written_together(out) as report:
        rows = table_rows(variants, base)
        report_md = markdown(variants, rows, runs, directories, base, " ".join(filter(None, (protocols, weights))))
        report.file(REPORT_MD, report_md.encode())
        report.file(REPORT_CSV, csv_text(rows).encode())
        report.file(REPORT_BUDGETS_CSV, budgets_csv_text(budget_rows(variants, base), csv_cell).encode())
        progress("drawing the plots")
        report.file(PSNR_PLOT, psnr_vs_time_png(variants))
        report.file(PARETO_PLOT, pareto_png(variants))
        report.file(DIFFERENCE_PLOT, difference_vs_time_png(variants, base))
        progress(f"writing the pictures of {len(views)} test views")
        with report.folder(REPORT_IMAGES) as folder:
            tiles = view_tiles(variants, views, folder)
        progress("writing the page")
        report.file(REPORT_HTML, page_html(report_md, PLOTS, tiles, VIEWS_NOTE).encode())
    return variants
