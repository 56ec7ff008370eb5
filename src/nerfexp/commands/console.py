"""What nerfexp's commands print: their own lines and progress bars, not their dependencies' notices, and
their errors as one line.

Lightning announces at INFO what nerfexp's own lines already say or what no run needs (the
accelerators found, a tip advertising a package, each checkpoint restored or saved without
``weights_only``); its warnings still show. Dependency warnings are filtered one by one, each by its
message, category and the module it is attributed to, so that a new warning is never hidden."""

import argparse
import contextlib
import logging
import sys
import warnings
from collections.abc import Callable, Iterator

from nerfexp.errors import NerfexpError

LIGHTNING_NOTICES = (  # loggers whose INFO lines are Lightning's notices (their warnings still show)
    "lightning.pytorch.utilities.rank_zero",  # GPU/TPU available, the litlogger tip, "Restoring states ..."
    "lightning.fabric.utilities.rank_zero",
    "lightning.pytorch.trainer.connectors.checkpoint_connector",  # "`weights_only` was not set ..."
)
DEPENDENCY_WARNINGS = (  # (message regex, category, module regex): warnings about a dependency's own code
    # torch deprecated LeafSpec (2.13 warns), which Lightning 2.6 still builds (lightning/pytorch/utilities/_pytree.py)
    (r"`isinstance\(treespec, LeafSpec\)` is deprecated", FutureWarning, r"lightning\.pytorch\.utilities\._pytree"),
    # Lightning's advice, on any machine with SLURM's commands, to start a run with srun (a PossibleUserWarning):
    # nerfexp's runs on SLURM go through hydra/launcher=slurm, which starts them with srun; one started
    # otherwise, on a login node or the test machine's own cluster, is meant to run where it is
    (r"The `srun` command is available on your system but is not used", Warning,
     r"lightning\.fabric\.plugins\.environments\.slurm"),
)


def quiet_dependencies() -> None:
    """Silence ``LIGHTNING_NOTICES``' INFO lines and ignore ``DEPENDENCY_WARNINGS``, for this process."""
    for name in LIGHTNING_NOTICES:
        logging.getLogger(name).setLevel(logging.WARNING)
    for message, category, module in DEPENDENCY_WARNINGS:
        warnings.filterwarnings("ignore", message=message, category=category, module=module)


@contextlib.contextmanager
def one_line_errors(prog: str) -> Iterator[None]:
    """Inside the block, a ``NerfexpError`` ends the program with ``PROG: error: MESSAGE`` and exit status 1."""
    try:
        yield
    except NerfexpError as error:
        sys.exit(f"{prog}: error: {error}")


def run_command(parser: argparse.ArgumentParser, argv: list[str] | None,
                work: Callable[[argparse.Namespace], str]) -> None:
    """A console script's body: parse ``argv`` with ``parser``, silence the dependencies' notices
    (``quiet_dependencies``), do ``work(args)`` and print the line it returns; a ``NerfexpError`` is one
    line (``one_line_errors``)."""
    args = parser.parse_args(argv)
    quiet_dependencies()
    with one_line_errors(parser.prog):
        summary = work(args)
    print(summary)
