"""Pieces of the console scripts' command lines: argument types, a run and its config changes."""

import argparse
import math
import sys
from collections.abc import Callable
from pathlib import Path

from omegaconf import DictConfig

from nerfexp.domains import bound_text
from nerfexp.errors import ConfigError
from nerfexp.memory import require_memory
from nerfexp.rundir.state import unfinished_line
from nerfexp.rundir.trained import run_config
from nerfexp.settings.checks import check_run_settings


def positive(kind: type, high: float | None = None) -> Callable[[str], int | float]:
    """An argparse type: a finite number of ``kind`` (int or float) above zero (nan and inf refused), and at
    most ``high`` where given (where the number stops meaning anything, said where the argument is made)."""
    def parse(text: str):
        value = kind(text)
        finite = not isinstance(value, float) or math.isfinite(value)  # a whole number of any size is finite
        if not finite or value <= 0 or (high is not None and value > high):
            upper = "" if high is None else f" and <= {bound_text(high)}"
            raise argparse.ArgumentTypeError(f"expected a finite number > 0{upper}, got {text}")
        return value
    return parse


def within(low: float, high: float) -> Callable[[str], float]:
    """An argparse type: a number in [``low``, ``high``] (nan and inf refused)."""
    def parse(text: str) -> float:
        value = float(text)
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"expected a number in [{bound_text(low)}, {bound_text(high)}], "
                                             f"got {text}")
        return value
    return parse


def port(text: str) -> int:
    """An argparse type: a TCP port, 1..65535, or 0 for any free one."""
    value = int(text)
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"expected a port in 1..65535 (0: any free one), got {text}")
    return value


def fitting(kind: Callable[[str], int], estimate: Callable[[int], int], what: str) -> Callable[[str], int]:
    """An argparse type: a ``kind`` value whose memory ``estimate(value)`` (bytes) fits in this machine's
    memory; ``what`` names the thing it sizes (``a grid of N^3 points``, N the value)."""
    def parse(text: str) -> int:
        value = kind(text)
        try:
            require_memory(text, what.replace("N", str(value)), estimate(value))
        except ConfigError as error:
            raise argparse.ArgumentTypeError(str(error)) from None
        return value
    return parse


def command_parser(prog: str, description: str) -> argparse.ArgumentParser:
    """The parser of the console script ``prog``, described by ``description`` (a docstring) without its
    reStructuredText markup: ``code`` reads as code."""
    return argparse.ArgumentParser(prog=prog, description=description.replace("``", ""))


def run_settings(run_dir: Path, overrides: list[str]) -> DictConfig:
    """The config of the run in ``run_dir`` with the user's ``KEY=VALUE`` ``overrides`` (``run_config``) to
    score its test views with, its settings checked as ``nerfexp`` checks a new run's (``check_run_settings``):
    a ConfigError naming the key as the user set it."""
    cfg = run_config(run_dir, overrides)
    check_run_settings(cfg, scoring=True)
    return cfg


def say_unfinished(prog: str, run_dir: Path, checkpoint: Path, step: int) -> None:
    """Print ``PROG: warning: ...`` where the run in ``run_dir`` did not finish (killed, failed, still running: its
    status read as what it is, ``nerfexp.rundir.state.unfinished_line``), so that what ``checkpoint``, at ``step``,
    is made of is said before it is used."""
    if (line := unfinished_line(run_dir, checkpoint, step)) is not None:
        print(f"{prog}: warning: {line}", file=sys.stderr, flush=True)


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """``RUN [KEY=VALUE ...]``: a run directory (or a checkpoint file in one) and changes to its config."""
    parser.add_argument("run", type=Path, help="a run directory (its checkpoints/last.ckpt), or a checkpoint file")
    parser.add_argument("overrides", nargs="*", metavar="KEY=VALUE",
                        help="changes to the run's config, e.g. data.root=/new/place/of/the/scene")


def add_chunk_argument(parser: argparse.ArgumentParser, also: str = "") -> None:
    """``--chunk N``: the rays a command that renders a trained run renders at once, which bounds its memory
    (checked when the run is loaded: ``nerfexp.products.trained.load_run``); ``also``: what else it sets there."""
    parser.add_argument("--chunk", type=positive(int),
                        help=f"rays rendered at once, which bounds the memory (default: the run's model.chunk){also}")
