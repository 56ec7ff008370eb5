"""What nerfexp's commands print: their own lines and progress bars, not their dependencies' notices, and
their errors as one line.

Lightning announces at INFO what nerfexp's own lines already say or what no run needs (the
accelerators found, a tip advertising a package, each checkpoint restored or saved without
``weights_only``); its warnings still show. Dependency warnings are filtered one by one, each by its
message, category and the module it is attributed to, so that a new warning is never hidden."""

import argparse
import contextlib
import errno
import logging
import os
import sys
import threading
import warnings
from collections.abc import Callable, Iterator

from nerfexp.commands.signals import ending_signals
from nerfexp.errors import NerfexpError
from nerfexp.files import WriteError

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


WRITING_ONLY = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG)  # errors only a write meets


def file_error_line(error: OSError) -> str:
    """One line for an OSError: ``PATH: cannot write (REASON)`` for a ``WriteError`` or an error only a write
    meets (``WRITING_ONLY``: a full disk, a read-only file system), else ``PATH: REASON``; without a file
    named, the reason alone."""
    reason = error.strerror or " ".join(str(error).split())  # one line whatever the message
    if not isinstance(error.filename, str | bytes | os.PathLike):
        return f"cannot write ({reason})" if error.errno in WRITING_ONLY else reason
    if isinstance(error, WriteError) or error.errno in WRITING_ONLY:
        return f"{os.fsdecode(error.filename)}: cannot write ({reason})"
    return f"{os.fsdecode(error.filename)}: {reason}"


def raised_within(error: BaseException | None, cause: BaseException) -> bool:
    """Whether ``cause`` is ``error`` or one of the errors it was raised from or while handling."""
    while error is not None:
        if error is cause:
            return True
        error = error.__cause__ or error.__context__
    return False


@contextlib.contextmanager
def thread_file_errors(prog: str) -> Iterator[None]:
    """Inside the block, an OSError that ends a background thread (a logger's writer: TensorBoard's event
    file on a full disk) prints no traceback. Its owner raises it again in the main thread (TensorBoard at
    its next write), where it is the block's error and said once, by the block's handler; one never raised
    there is said after the block as ``PROG: warning: a background thread stopped: file_error_line``.
    Other errors of threads are Python's to print, as before the block."""
    stopped: list[OSError] = []
    previous = threading.excepthook

    def keep(args: threading.ExceptHookArgs) -> None:
        if isinstance(args.exc_value, OSError):
            stopped.append(args.exc_value)
        else:
            previous(args)

    threading.excepthook = keep
    raised = None
    try:
        yield
    except BaseException as error:
        raised = error
        raise
    finally:
        threading.excepthook = previous
        for error in stopped:
            if not raised_within(raised, error):
                print(f"{prog}: warning: a background thread stopped: {file_error_line(error)}", file=sys.stderr)


@contextlib.contextmanager
def one_line_errors(prog: str) -> Iterator[None]:
    """Inside the block, a ``NerfexpError`` ends the program with ``PROG: error: MESSAGE`` and exit status 1,
    an OSError (a file that cannot be written or read) with ``PROG: error: file_error_line``, and SIGINT or
    SIGTERM with ``PROG: stopped (SIGNAL)`` and exit status 128 + the signal (``ending_signals``); a
    background thread's OSError is no traceback either (``thread_file_errors``). What the block was writing
    is left as it was (``nerfexp.files``' atomic writes)."""
    with ending_signals(prog), thread_file_errors(prog):
        try:
            yield
        except NerfexpError as error:
            sys.exit(f"{prog}: error: {error}")
        except OSError as error:
            sys.exit(f"{prog}: error: {file_error_line(error)}")


def run_command(parser: argparse.ArgumentParser, argv: list[str] | None,
                work: Callable[[argparse.Namespace], str]) -> None:
    """A console script's body: parse ``argv`` with ``parser``, silence the dependencies' notices
    (``quiet_dependencies``), do ``work(args)`` and print the line it returns; a ``NerfexpError``, an
    OSError or a signal is one line (``one_line_errors``)."""
    args = parser.parse_args(argv)
    quiet_dependencies()
    with one_line_errors(parser.prog):
        summary = work(args)
    print(summary)
