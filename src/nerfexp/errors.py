"""Errors that nerfexp reports to the user as one clear line instead of a traceback."""

import contextlib
from collections.abc import Iterator


class NerfexpError(Exception):
    """Base class: bad input or a run that cannot continue, with a message that says what and where."""


class ConfigError(NerfexpError):
    """A config value is missing or unusable; the message names the key."""


class DatasetError(NerfexpError):
    """A dataset is missing or malformed; the message names the file or key and what was expected."""


class NonFiniteError(NerfexpError):
    """Training produced a NaN or infinity; the message names the step, the quantity and the component."""


class FieldCollapseError(NerfexpError):
    """A network's density field went to zero everywhere and stayed there; the message names the step,
    the network and what to try."""


def failure_text(check: str, error: BaseException) -> str:
    """One line saying that ``check`` (``the settings check``) failed with ``error``, an exception it did not
    raise on purpose: its type and its message, on one line."""
    return f"{check} failed on this config ({type(error).__name__}: {' '.join(str(error).split())})"


@contextlib.contextmanager
def failures_refused(check: str) -> Iterator[None]:
    """Inside the block, which checks the user's input before any work, an exception other than a NerfexpError or
    an OSError (a file that cannot be read, which the commands say in one line naming it) is a ConfigError saying
    that ``check`` failed (``failure_text``): a check that fails refuses, never lets the work go on unchecked."""
    try:
        yield
    except (NerfexpError, OSError):
        raise
    except Exception as error:
        raise ConfigError(failure_text(check, error)) from error


@contextlib.contextmanager
def callback_refusals(check: str) -> Iterator[None]:
    """Inside the block, a Hydra callback's check (``check``: its name, in words), any exception ends the program
    with ``SystemExit("nerfexp: error: ...")``: a NerfexpError's message, any other's ``failure_text``. Hydra turns
    an exception of a callback into a warning and goes on with the run; SystemExit it lets through."""
    try:
        yield
    except NerfexpError as error:
        raise SystemExit(f"nerfexp: error: {error}") from None
    except Exception as error:
        raise SystemExit(f"nerfexp: error: {failure_text(check, error)}") from None
