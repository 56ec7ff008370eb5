"""The report's folder: what it may already hold (``check_out``: of the files the report writes over,
none a user made), and every file of the report written into it (``write_report``; what they are: the
package's docstring), each recorded in the folder's manifest as it is written (``nerfexp.manifest``)."""


from pathlib import Path

from nerfexp import manifest
from nerfexp.files import atomic_directory
from nerfexp.report.budget_tables import budget_rows, budgets_csv_text
from nerfexp.report.lpips_weights import vouched_lpips
from nerfexp.report.page import page_html
from nerfexp.report.pictures import PLOTS, VIEWS_NOTE, check_views, view_tiles
from nerfexp.report.plots import difference_vs_time_png, pareto_png, psnr_vs_time_png
from nerfexp.report.protocols import compared_runs
from nerfexp.report.runs import find_runs
from nerfexp.report.tables import csv_cell, csv_text, markdown, table_rows
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
                 reference: str | None = None, views: list[int] | None = None) -> list[Variant]:
    """The report of the runs under ``directories`` in ``out``; ``reference``: the variant the others are
    compared with (see ``reference_variant``); ``views``: the test views on the page (``check_views``);
    ``out`` is checked first (``check_out``)."""
    check_out(out)
    runs, protocols = compared_runs(find_runs(directories))  # the scores compared: of one protocol
    runs, weights = vouched_lpips(runs)  # LPIPS only of the published weights
    variants = group_variants([run for run in runs if run.overrides is not None], over)
    base = reference_variant(variants, reference)
    views = check_views(variants, views)
    rows = table_rows(variants, base)
    report_md = markdown(variants, rows, runs, directories, base, " ".join(filter(None, (protocols, weights))))
    manifest.write(out, REPORT_MD, report_md.encode())
    manifest.write(out, REPORT_CSV, csv_text(rows).encode())
    manifest.write(out, REPORT_BUDGETS_CSV, budgets_csv_text(budget_rows(variants, base), csv_cell).encode())
    manifest.write(out, PSNR_PLOT, psnr_vs_time_png(variants))
    manifest.write(out, PARETO_PLOT, pareto_png(variants))
    manifest.write(out, DIFFERENCE_PLOT, difference_vs_time_png(variants, base))
    with atomic_directory(out / REPORT_IMAGES, replace=True) as folder:
        tiles = view_tiles(variants, views, folder)
    manifest.record_folder(out, REPORT_IMAGES)
    manifest.write(out, REPORT_HTML, page_html(report_md, PLOTS, tiles, VIEWS_NOTE).encode())
    return variants
