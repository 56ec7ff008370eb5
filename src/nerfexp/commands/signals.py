"""A command ended by a signal exits as shells report it: 128 + the signal's number (143 for SIGTERM, a
SLURM time limit or ``kill``; 130 for SIGINT, Ctrl-C), never 0, and says which signal it was.

Lightning turns SIGTERM during ``fit`` into a ``SystemExit`` without a code (exit status 0) and SIGINT
into ``SystemExit(1)``; outside ``fit`` SIGTERM would end the process before a run could record it.
``ending_signals`` installs a handler for both that records the signal and raises (``Signalled`` for
SIGTERM, ``KeyboardInterrupt`` for SIGINT), so the run's ``except`` blocks record it; Lightning keeps
calling the handler found before its own, so this holds inside ``fit`` too.
"""

import contextlib
import signal
import sys
from collections.abc import Iterator

ENDING = (signal.SIGTERM, signal.SIGINT)
_received: list[int] = []  # the signals received inside ``ending_signals``, in order


class Signalled(BaseException):
    """Raised by the handler of a signal that ends the command (not an ``Exception``: nothing that
    catches errors to go on, e.g. a sweep's next job, may catch it)."""

    def __init__(self, signum: int):
        super().__init__(f"ended by {signal.Signals(signum).name}")
        self.signum = signum


def received_signal() -> str | None:
    """The name of the first ending signal received (e.g. ``SIGTERM``), or None."""
    return signal.Signals(_received[0]).name if _received else None


def _handle(signum: int, frame) -> None:
    _received.append(signum)
    if signum == signal.SIGINT:
        raise KeyboardInterrupt
    raise Signalled(signum)


@contextlib.contextmanager
def ending_signals() -> Iterator[None]:
    """Inside the block SIGTERM and SIGINT raise (see the module's docstring); whatever the block then
    raises ends the process with exit status 128 + the signal's number. The handlers found before are
    restored after it."""
    _received.clear()
    previous = {signum: signal.signal(signum, _handle) for signum in ENDING}
    try:
        yield
    except BaseException:
        if not _received:
            raise
        sys.exit(128 + _received[0])
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
