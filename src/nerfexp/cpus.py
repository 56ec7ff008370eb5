"""The CPUs this process may use, and the thread counts they bound: torch's intra-op threads
(``nerfexp.machine_share``) and COLMAP's (``nerfexp.data.colmap_sfm``).

A count asked for above the CPUs this process may use (``threads=64``, ``OMP_NUM_THREADS=64``, ``data.threads=64``
on a machine, or under a scheduler's affinity, that grants 16) is capped at them, with a line saying so, rather than
refused: threads beyond the CPUs only wait on each other, so the count decides how fast the work goes, not what it
computes (but for the last digits of a parallel sum, whose order it may change; a resumed run may change it too:
``nerfexp.training.resume``), and a config written for a larger node still runs on a smaller one. A count beyond
any machine (``nerfexp.domains.THREAD_LIMIT``) is a mistake, which the settings check refuses before any work.
"""

import os


def allowed_cpus() -> set[int] | None:
    """The CPUs this process may run on (``os.sched_getaffinity``), or None where the system does not say."""
    try:
        return os.sched_getaffinity(0)
    except (AttributeError, OSError):
        return None


def available_cpus() -> int:
    """How many CPUs this process may use: its affinity's, else ``os.cpu_count()``, at least 1."""
    allowed = allowed_cpus()
    return len(allowed) if allowed else os.cpu_count() or 1


def capped_line(asked: str, requested: int, cpus: int) -> str | None:
    """The line saying that ``requested`` threads (asked for by ``asked``, as the user wrote it) are capped at the
    ``cpus`` this process may use; None where they are no more than those.

    >>> capped_line("threads=64", 64, 2).split(" (")[0]
    'threads=64: more threads than the 2 CPUs this process may use; 2 run'
    >>> capped_line("threads=2", 2, 16) is None
    True
    """
    if requested <= cpus:
        return None
    return (f"{asked}: more threads than the {cpus} CPUs this process may use; {cpus} run (threads beyond the CPUs "
            "only wait on each other)")
