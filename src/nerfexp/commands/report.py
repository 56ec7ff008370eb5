"""``nerfexp-report``: a sweep's variants side by side, their quality against the compute they cost
(what it writes: ``nerfexp.report``)."""


import argparse
import sys
from pathlib import Path

from nerfexp.commands.arguments import command_parser
from nerfexp.commands.console import one_line_errors
from nerfexp.report.folder import write_report
from nerfexp.report.pictures import VIEWS_SHOWN
from nerfexp.report.shared_machines import timing_caveats
from nerfexp.rundir.layout import REPORT_HTML, REPORT_MD


def build_parser() -> argparse.ArgumentParser:
    """The ``nerfexp-report`` command line (the module's first paragraph describes it)."""
    parser = command_parser("nerfexp-report", __doc__.split("\n\n")[0])
    parser.add_argument("dirs", nargs="+", type=Path, help="multirun or run directories")
    parser.add_argument("--out", type=Path, help="where to write the report (default: the first directory)")
    parser.add_argument("--over", nargs="+", default=["seed"],
                        help="override keys averaged over within a variant (default: seed; seed data.scene: each "
                             "variant's mean over the scenes of a sweep over them, as the paper's table)")
    parser.add_argument("--reference", metavar="VARIANT",
                        help="the variant the others are compared with, by its label in the report (e.g. "
                             "'encoding=posenc, hierarchical=true'); default: ablation=complete if in the sweep")
    parser.add_argument("--views", nargs="+", type=int, metavar="INDEX",
                        help="test views shown in report.html, each variant's render beside the ground truth "
                             f"(default: {VIEWS_SHOWN} spread from the first to the last)")
    return parser


def say(line: str) -> None:
    """A line of the command's progress on standard error, at once (a long report is never silent)."""
    print(f"nerfexp-report: {line}", file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> None:
    """The ``nerfexp-report`` command (``build_parser``)."""
    args = build_parser().parse_args(argv)
    out = args.out or args.dirs[0]
    with one_line_errors("nerfexp-report"):
        variants = write_report(args.dirs, out, tuple(args.over), args.reference, args.views, progress=say)
    for line in timing_caveats(variants):  # report.md says it too, below the table
        say(line)
    print(f"{len(variants)} variants; report in {out / REPORT_MD} and {out / REPORT_HTML}", file=sys.stderr)
