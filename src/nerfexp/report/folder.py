"""The report's folder: what it may already hold (``check_out``: nothing a user made), and every file of
the report written into it (``write_report``; what they are: the package's docstring)."""


from pathlib import Path

from nerfexp.errors import NerfexpError
from nerfexp.files import TEMPORARY, atomic_directory, atomic_write, folder_entries, foreign_message, is_made
from nerfexp.report.page import page_html
from nerfexp.report.pictures import PLOTS, VIEWS_NOTE, check_views, view_tiles
from nerfexp.report.plots import pareto_png, psnr_vs_time_png
from nerfexp.report.runs import find_runs
from nerfexp.report.tables import csv_text, markdown, table_rows
from nerfexp.report.variants import Variant, group_variants, reference_variant
from nerfexp.rundir.layout import (
    PARETO_PLOT,
    PSNR_PLOT,
    REPORT_CSV,
    REPORT_HTML,
    REPORT_IMAGES,
    REPORT_MADE,
    REPORT_MD,
    RUN_MADE,
    SWEEP_MADE,
    find_run_dirs,
)


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
    rows = table_rows(variants, base)
    report_md = markdown(variants, rows, runs, directories, base)
    atomic_write(out / REPORT_MD, report_md.encode())
    atomic_write(out / REPORT_CSV, csv_text(rows).encode())
    atomic_write(out / PSNR_PLOT, psnr_vs_time_png(variants))
    atomic_write(out / PARETO_PLOT, pareto_png(variants))
    with atomic_directory(out / REPORT_IMAGES, replace=True) as folder:
        tiles = view_tiles(variants, views, folder)
    atomic_write(out / REPORT_HTML, page_html(report_md, PLOTS, tiles, VIEWS_NOTE).encode())
    return variants
