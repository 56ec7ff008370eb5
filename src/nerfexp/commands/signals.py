"""A command ended by a signal exits as shells report it: 128 + the signal's number (143 for SIGTERM, a
SLURM time limit or ``kill``; 130 for SIGINT, Ctrl-C), never 0, and says which signal it was.

Lightning turns SIGTERM during ``fit`` into a ``SystemExit`` without a code (exit status 0) and SIGINT
into ``SystemExit(1)``; outside ``fit`` SIGTERM would end the process before a run could record it.
``ending_signals`` installs a handler for both that records the signal and raises (``Signalled`` for
SIGTERM, ``KeyboardInterrupt`` for SIGINT), so the run's ``except`` blocks record it; Lightning keeps
calling the handler found before its own, so this holds inside ``fit`` too.

A sweep's job that submitit started in a process of its own (``hydra/launcher=slurm`` or ``submitit_local``)
never runs ``cli``: ``job_signals`` gives it the same SIGTERM handling in place of submitit's, which ignores
SIGTERM, and only logs the notice submitit asks SLURM to send ``hydra.launcher.signal_delay_s`` before the
time limit (USR2), which submitit would turn into an ``UncompletedJobError`` raised wherever training was.
The job then ends with ``JobSignalled``, an ``Exception``: Hydra records the job as failed, submitit
returns it to the sweep, and the other jobs go on (a ``BaseException`` would leave submitit nothing to return).
"""

import contextlib
import logging
import os
import signal
import sys
from collections.abc import Iterator

from nerfexp.errors import NerfexpError

ENDING = (signal.SIGTERM, signal.SIGINT)
_received: list[int] = []  # the signals received inside ``ending_signals`` or ``job_signals``, in order
NOTICE_SIGNAL = "SUBMITIT_PREEMPT_SIGNAL"  # submitit's variable naming its notice signal (USR2 where unset)
log = logging.getLogger("nerfexp")


class Signalled(BaseException):
    """Raised by the handler of a signal that ends the command (not an ``Exception``: nothing that
    catches errors to go on, e.g. a sweep's next job, may catch it)."""

    def __init__(self, signum: int):
        super().__init__(f"ended by {signal.Signals(signum).name}")
        self.signum = signum


class JobSignalled(NerfexpError):
    """A launcher's job ended by a signal (``job_signals``); the message names the run and how to continue it."""


def received_signal() -> str | None:
    """The name of the first ending signal received (e.g. ``SIGTERM``), or None."""
    return signal.Signals(_received[0]).name if _received else None


def _handle(signum: int, frame) -> None:
    _received.append(signum)
    if signum == signal.SIGINT:
        raise KeyboardInterrupt
    raise Signalled(signum)


@contextlib.contextmanager
def ending_signals(prog: str | None = None) -> Iterator[None]:
    """Inside the block SIGTERM and SIGINT raise (see the module's docstring); whatever the block then
    raises ends the process with exit status 128 + the signal's number, after the line ``PROG: stopped
    (SIGNAL)`` on standard error where ``prog`` is given (an enclosing block says it, or the command
    itself). The handlers found before are restored after it. A block inside another (a console script's
    entry point, ``nerfexp.commands.start``, holds one around the whole command) leaves it all to that one,
    so the line is said once."""
    if signal.getsignal(signal.SIGINT) is _handle:  # inside another block: that one ends the process
        yield
        return
    _received.clear()
    previous = {signum: signal.signal(signum, _handle) for signum in ENDING}
    try:
        yield
    except BaseException:
        if not _received:
            raise
        if prog is not None:
            print(f"{prog}: stopped ({received_signal()})", file=sys.stderr, flush=True)
        sys.exit(128 + _received[0])
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def in_launcher_job() -> bool:
    """Whether this process is a job that submitit started (it exports ``SUBMITIT_EXECUTOR``: slurm or local)."""
    return bool(os.environ.get("SUBMITIT_EXECUTOR"))


def _log_notice(signum: int, frame) -> None:
    log.warning("%s: SLURM's notice that the job nears its time limit (or is preempted); the run goes on "
                "until SIGTERM ends it", signal.Signals(signum).name)


@contextlib.contextmanager
def job_signals() -> Iterator[None]:
    """Inside a launcher's job (``in_launcher_job``), SIGTERM raises ``Signalled`` after recording itself
    (``received_signal``) and submitit's notice signal is only logged (see the module's docstring); the
    handlers found before are restored after the block. Elsewhere the block runs as it is."""
    if not in_launcher_job():
        yield
        return
    _received.clear()
    notice = signal.Signals[f"SIG{os.environ.get(NOTICE_SIGNAL, 'USR2')}"]
    previous = {signal.SIGTERM: signal.signal(signal.SIGTERM, _handle), notice: signal.signal(notice, _log_notice)}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
