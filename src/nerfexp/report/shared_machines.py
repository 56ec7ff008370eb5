"""Whether the runs a report compares by time may be compared so: all on one machine (results.json's ``machine``: its
host and device, the device naming the CPU or GPU and torch's threads), and each with that machine to itself. A run
beside other work (another training job, a build, a shared node) trains slower than its components do, and its
``results.json`` says so in ``other_load`` (other processes' mean busy CPUs while it trained,
``nerfexp.machine_share``); a run that did not measure it (an earlier nerfexp's, a system without CPU
counters) is not said to have shared.

The report compares by time (the per-budget table's time columns, the equal-time ranking, the difference-against-time
plot) only the variants ``timed_labels`` names, and says why once, below its table (``timing_caveats``): so that a
time ratio that is partly the neighbours', or the other machine's, is never read as the components'.
"""

from nerfexp.report.runs import Run
from nerfexp.report.variants import Variant
from nerfexp.rundir.records import SHARED_LOAD


def machine(run: Run) -> tuple[str, str] | None:
    """(host, device) of a finished run, where its results.json records them."""
    recorded = (run.results or {}).get("machine")
    return None if recorded is None else (recorded["host"], recorded["device"])


def machines(variants: list[Variant]) -> list[tuple[str, str]]:
    """The machines the variants' finished runs recorded, each once, sorted."""
    return sorted({found for v in variants for run in v.finished if (found := machine(run)) is not None})


def shared(run: Run) -> float | None:
    """The ``other_load`` of a finished run that shared its machine (above ``SHARED_LOAD``), else None."""
    load = (run.results or {}).get("other_load")
    return load if load is not None and load > SHARED_LOAD else None


def timed_labels(variants: list[Variant]) -> set[str]:
    """The labels of the variants whose times may be compared with each other: none where the finished runs come
    from more than one machine (``machines``), else those with finished runs none of which shared it (``shared``)."""
    if len(machines(variants)) > 1:
        return set()
    return {v.label for v in variants if v.finished and all(shared(run) is None for run in v.finished)}


def timing_caveats(variants: list[Variant]) -> list[str]:
    """What the report's times need said, each once: the runs come from several machines (none is compared by time);
    runs shared their machine (``shared_text``: named with their others' load; their variants' times are partly
    their neighbours', and those variants are compared by step only). None where neither holds."""
    runs = [run for v in variants for run in v.finished]
    caveats = []
    if len(found := machines(variants)) > 1:
        where = "; ".join(f"{host}: {device}" for host, device in found)
        caveats.append(f"The runs come from {len(found)} machines ({where}): their times are not comparable with each "
                       "other, so no variant is compared with another by time (by step only).")
    loads = [(run, load) for run in runs if (load := shared(run)) is not None]
    if loads:
        untimed = [v.label for v in variants if any(shared(run) is not None for run in v.finished)]
        step_only = ("" if caveats else ", so no variant is compared with another by time (by step only)"
                     if len(untimed) == sum(bool(v.finished) for v in variants)
                     else f", and {'; '.join(untimed)} compared with others by step only")
        caveats.append(f"{shared_text(loads, len(runs))}: their times, in the table and the plots, are partly their "
                       f"neighbours'{step_only}.")
    return caveats


def shared_text(loads: list[tuple[Run, float]], n_runs: int) -> str:
    """Which of ``n_runs`` finished runs shared their machine, with the others' load (``loads``: each such run with
    its ``shared``): each named where some did; where every one of several did, how many and the loads' range (a
    list of every run would name nothing the reader needs to find)."""
    if len(loads) == n_runs > 1:
        low, high = min(load for _, load in loads), max(load for _, load in loads)
        return (f"All {n_runs} finished runs shared their machine (other processes kept {low:.2f} to {high:.2f} CPUs "
                f"busy on average while they trained, more than {SHARED_LOAD:g})")
    named = ", ".join(f"`{run.path}` ({load:.2f})" for run, load in loads)
    return (f"{len(loads)} of the {n_runs} finished runs shared their machine (other processes kept more than "
            f"{SHARED_LOAD:g} CPU busy on average while they trained: {named})")
