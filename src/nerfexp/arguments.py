"""Pieces of the console scripts' command lines: argument types, a run and its config changes."""

import argparse
from collections.abc import Callable
from pathlib import Path


def positive(kind: type) -> Callable[[str], int | float]:
    """An argparse type: a number of ``kind`` (int or float) above zero."""
    def parse(text: str):
        value = kind(text)
        if value <= 0:
            raise argparse.ArgumentTypeError(f"expected a positive number, got {text}")
        return value
    return parse


def command_parser(prog: str, description: str) -> argparse.ArgumentParser:
    """The parser of the console script ``prog``, described by ``description`` (a docstring) without its
    reStructuredText markup: ``code`` reads as code."""
    return argparse.ArgumentParser(prog=prog, description=description.replace("``", ""))


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """``RUN [KEY=VALUE ...]``: a run directory (or a checkpoint file in one) and changes to its config."""
    parser.add_argument("run", type=Path, help="a run directory (its checkpoints/last.ckpt), or a checkpoint file")
    parser.add_argument("overrides", nargs="*", metavar="KEY=VALUE",
                        help="changes to the run's config, e.g. data.root=/new/place/of/the/scene")
