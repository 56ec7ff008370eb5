"""Each console script's entry point (``pyproject.toml``'s ``[project.scripts]``): the signals that end a command
are handled from its first moment. A command's module imports torch, Lightning, Hydra or matplotlib, seconds on
a small CPU, before its own handlers are set; the entry points here import only ``nerfexp.commands.signals``,
hold ``ending_signals`` around the whole command, and only then import it. So Ctrl-C while a command is still
starting ends it as it would later: ``PROG: stopped (SIGINT)`` and exit status 130 (143 for SIGTERM), never a
traceback. The command's own blocks inside leave the line to this one (``ending_signals``). Each takes the
command's arguments as its command does (``argv``, None: the process's), ``nerfexp``'s Hydra reads them itself."""

from nerfexp.commands.signals import ending_signals


def train() -> None:
    """``nerfexp`` (``nerfexp.commands.train.cli``)."""
    with ending_signals("nerfexp"):
        from nerfexp.commands.train import cli
        cli()


def evaluate(argv: list[str] | None = None) -> None:
    """``nerfexp-eval`` (``nerfexp.commands.evaluate``)."""
    with ending_signals("nerfexp-eval"):
        from nerfexp.commands.evaluate import main
        main(argv)


def render(argv: list[str] | None = None) -> None:
    """``nerfexp-render`` (``nerfexp.commands.render``)."""
    with ending_signals("nerfexp-render"):
        from nerfexp.commands.render import main
        main(argv)


def report(argv: list[str] | None = None) -> None:
    """``nerfexp-report`` (``nerfexp.commands.report``)."""
    with ending_signals("nerfexp-report"):
        from nerfexp.commands.report import main
        main(argv)


def scene(argv: list[str] | None = None) -> None:
    """``nerfexp-scene`` (``nerfexp.commands.scene``)."""
    with ending_signals("nerfexp-scene"):
        from nerfexp.commands.scene import main
        main(argv)


def export(argv: list[str] | None = None) -> None:
    """``nerfexp-export`` (``nerfexp.commands.export``)."""
    with ending_signals("nerfexp-export"):
        from nerfexp.commands.export import main
        main(argv)


def view(argv: list[str] | None = None) -> None:
    """``nerfexp-view`` (``nerfexp.commands.view``)."""
    with ending_signals("nerfexp-view"):
        from nerfexp.commands.view import main
        main(argv)


def data(argv: list[str] | None = None) -> None:
    """``nerfexp-data`` (``nerfexp.commands.data``)."""
    with ending_signals("nerfexp-data"):
        from nerfexp.commands.data import main
        main(argv)
