"""Whether the runs a report compares by time had their machine to themselves: a run beside other work (another
training job, a build, a shared node) trains slower than its components do, and its ``results.json`` says so in
``other_load`` (other processes' mean busy CPUs while it trained, ``nerfexp.machine_share``). Each
comparison by time that holds such a run gets one line naming them (``shared_lines``), so that a time ratio
that is partly the neighbours' is never read as the components'. Runs that did not measure it (an earlier
nerfexp's, a system without CPU counters) are not said to have shared."""

from nerfexp.report.runs import Run
from nerfexp.report.variants import Variant
from nerfexp.rundir.layout import PARETO_PLOT, PSNR_PLOT
from nerfexp.rundir.records import SHARED_LOAD

# The report's comparisons by time, each of every variant's finished runs
TIME_COMPARISONS = ("the table's train time, s / step and rays / s", f"`{PSNR_PLOT}`", f"`{PARETO_PLOT}`")


def shared(run: Run) -> float | None:
    """The ``other_load`` of a finished run that shared its machine (above ``SHARED_LOAD``), else None."""
    load = (run.results or {}).get("other_load")
    return load if load is not None and load > SHARED_LOAD else None


def shared_line(comparison: str, runs: list[Run]) -> str | None:
    """The line for one ``comparison`` by time of ``runs`` where some of them shared their machine, else None
    (and None for fewer than two runs: nothing is compared)."""
    loads = [(run, load) for run in runs if (load := shared(run)) is not None]
    if not loads or len(runs) < 2:
        return None
    named = ", ".join(f"`{run.path}` ({load:.2f})" for run, load in loads)
    return (f"{comparison}: {len(loads)} of its {len(runs)} runs shared their machine (other processes kept more "
            f"than {SHARED_LOAD:g} CPU busy on average while they trained: {named}), so time ratios involving them "
            "are not the components' own.")


def shared_lines(variants: list[Variant]) -> list[str]:
    """One line per comparison by time (``TIME_COMPARISONS``) whose runs, every variant's finished ones, include
    some that shared their machine (``shared_line``); none where no run did."""
    runs = [run for variant in variants for run in variant.finished]
    return [line for comparison in TIME_COMPARISONS if (line := shared_line(comparison, runs)) is not None]
