"""How much of the machine a run had while it trained: its own CPU time beside its wall time, how busy other
processes kept the CPUs it may use (the system's counters, Linux's ``/proc/stat``, against the run's own CPU
time), and the torch threads it runs with.

Naming: a ``Sample`` is read at one moment: ``wall_s`` (``time.perf_counter``), ``cpu_s`` (this process's user +
system CPU seconds, all its threads: ``time.process_time``) and ``busy_s`` (CPU seconds that the CPUs this process
may use spent busy since boot, every process's together; None where the system has no such counters). Between two
samples, the others' busy CPU seconds are ``busy_s`` - ``cpu_s``, and their mean load (``other_load``) those
seconds over the wall seconds: the number of CPUs other processes kept busy on average (0.5: half a CPU).

Why it matters: a run beside other work trains slower than its components do, and torch's OpenMP threads, one per
core by default, wait on each other once the cores are oversubscribed (docs/acceleration.md). So the thread
count is chosen from the CPUs this process may use and the jobs a local multirun starts at once
(``intra_op_threads``), and a run says at its start when the machine is already busy (``busy_line``). A single
run's automatic choice then follows the machine while it trains (``follow_load``, which
``nerfexp.training.callbacks.ThreadsFollowLoad`` asks every ``FOLLOW_WINDOW_S``): a neighbour that starts later,
or a busy moment at the start that passed, changes the thread count instead of deciding it for the whole run.
"""

import math
import os
import time
from collections.abc import Iterable
from pathlib import Path
from typing import NamedTuple

import torch

from nerfexp.cpus import allowed_cpus, available_cpus, capped_line

PROC_STAT = Path("/proc/stat")
# A cpuN line of /proc/stat: user nice system idle iowait irq softirq steal guest guest_nice (clock ticks since
# boot); guest and guest_nice are counted in user and nice already, so only the first 8 are summed
COUNTERS = 8
IDLE = (3, 4)  # idle and iowait: the CPU ran nothing
BUSY_LOAD = 0.5  # ... above which a run says at its start that the machine is already busy
BUSY_SAMPLE_S = 0.3  # seconds over which the machine is looked at before training (``busy_line``)
THREADS_VARIABLE = "OMP_NUM_THREADS"  # a user's own thread count, which torch also reads at import
JOBLIB_LAUNCHER = "JoblibLauncher"  # Hydra's joblib launcher (hydra/launcher=joblib): n_jobs runs at once
FOLLOW_WINDOW_S = 10.0  # seconds of training between two looks at the machine (``follow_load``)


class Sample(NamedTuple):
    wall_s: float
    cpu_s: float
    busy_s: float | None


def busy_ticks(stat_text: str, cpus: Iterable[int] | None = None) -> int | None:
    """Clock ticks that the CPUs ``cpus`` (None: every one listed) spent busy since boot, from a ``/proc/stat``
    text: the sum over their ``cpuN`` lines of the first ``COUNTERS`` counters but idle and iowait. None where the
    text lists none of them (no counters to read: never a guess).

    >>> busy_ticks("cpu  9 0 9 90 0 0 0 0 0 0\\ncpu0 3 1 2 50 4 1 0 0 0 0\\ncpu1 6 0 7 40 0 0 0 0 0 0\\n", [1])
    13
    """
    wanted = None if cpus is None else set(cpus)
    total, found = 0, False
    for line in stat_text.splitlines():
        name, *counters = line.split()
        if not (name.startswith("cpu") and name[3:].isdigit()) or (wanted is not None and int(name[3:]) not in wanted):
            continue
        values = [int(value) for value in counters[:COUNTERS]]
        total += sum(values) - sum(values[i] for i in IDLE if i < len(values))
        found = True
    return total if found else None


def read_busy_s(stat: Path = PROC_STAT) -> float | None:
    """``busy_ticks`` of the CPUs this process may use, in seconds; None where ``stat`` cannot be read or lists
    none of them (not Linux)."""
    try:
        ticks = busy_ticks(stat.read_text(), allowed_cpus())
        per_second = os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, AttributeError):
        return None
    return None if ticks is None else ticks / per_second


def sample(stat: Path = PROC_STAT) -> Sample:
    """This moment's ``Sample``."""
    return Sample(time.perf_counter(), time.process_time(), read_busy_s(stat))


def others_cpu_s(start: Sample, end: Sample) -> float | None:
    """CPU seconds that other processes kept the allowed CPUs busy from ``start`` to ``end``: the system's busy
    seconds less this process's own, at least 0 (the counters tick in hundredths of a second, and this process
    may run on CPUs outside the sum once its affinity changes); None where either sample has no counters.

    >>> others_cpu_s(Sample(0.0, 1.0, 100.0), Sample(10.0, 9.0, 120.0))  # 20 busy, 8 of them this process's
    12.0
    """
    if start.busy_s is None or end.busy_s is None:
        return None
    return max(0.0, (end.busy_s - start.busy_s) - (end.cpu_s - start.cpu_s))


def other_load(others_s: float | None, wall_s: float) -> float | None:
    """The mean number of CPUs other processes kept busy: ``others_s`` (``others_cpu_s``, summed over the
    training) over ``wall_s``; None where it was not measured or no time passed.

    >>> other_load(12.0, 10.0)
    1.2
    """
    return None if others_s is None or not wall_s > 0 else others_s / wall_s


def busy_line(start: Sample, end: Sample, cpus: int) -> str | None:
    """The line a run logs at its start where other processes kept more than ``BUSY_LOAD`` CPUs busy from
    ``start`` to ``end`` (two samples a fraction of a second apart), of the ``cpus`` it may use; else None."""
    load = other_load(others_cpu_s(start, end), end.wall_s - start.wall_s)
    if load is None or load <= BUSY_LOAD:
        return None
    return (f"the machine is already busy: other processes keep {load:.1f} of the {cpus} CPUs this run may use busy; "
            f"its times will be slower than the components' and results.json records them as shared (other_load)")


def intra_op_threads(available_cpus: int, parallel_jobs: int, requested: int | None, busy_cpus: float = 0.0) -> int:
    """Torch's intra-op threads: ``requested`` where the user gave a number, at most the CPUs this process may use
    (``nerfexp.cpus``: threads beyond the cores wait on each other), else those CPUs shared among the jobs that run
    at once, at least 1. A single job also leaves out the CPUs other processes kept busy when it started
    (``busy_cpus``, rounded to the nearest whole CPU); jobs of one multirun start together, so their division is
    theirs alone.

    >>> intra_op_threads(16, 3, None), intra_op_threads(2, 4, None), intra_op_threads(8, 1, 6)
    (5, 1, 6)
    >>> intra_op_threads(2, 1, 6)  # capped at the CPUs
    2
    >>> intra_op_threads(2, 1, None, busy_cpus=1.97), intra_op_threads(8, 1, None, busy_cpus=0.4)
    (1, 8)
    """
    if requested is not None:
        return min(requested, available_cpus)
    free = available_cpus - math.floor(busy_cpus + 0.5) if parallel_jobs == 1 else available_cpus
    return max(1, free // max(1, parallel_jobs))


def parallel_jobs(launcher: dict | None, available_cpus: int) -> int:
    """How many jobs the multirun ``launcher`` (its config: ``hydra.launcher``) starts at once on this machine:
    Hydra's joblib launcher its ``n_jobs`` (joblib's reading: -1 one per CPU, -2 all but one, ...), every other
    launcher one (the basic launcher runs one job after another; a cluster's jobs each have CPUs of their own).

    >>> parallel_jobs({"_target_": "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher",
    ...                "n_jobs": -1}, 8)
    8
    """
    if not launcher or not str(launcher.get("_target_", "")).endswith(JOBLIB_LAUNCHER):
        return 1
    jobs = launcher.get("n_jobs")
    if not isinstance(jobs, int) or isinstance(jobs, bool) or jobs == 0:
        return 1
    return jobs if jobs > 0 else max(1, available_cpus + 1 + jobs)


def requested_threads(setting: int | None, environment: dict) -> int | None:
    """The thread count the user asked for: the ``threads`` setting, else ``OMP_NUM_THREADS`` where it is a
    whole number >= 1 (of any size: ``intra_op_threads`` caps it at the CPUs); None (auto) otherwise."""
    if setting is not None:
        return setting
    value = environment.get(THREADS_VARIABLE, "").strip()
    return int(value) if value.isascii() and value.isdigit() and int(value) >= 1 else None


def asked_for(setting: int | None, requested: int) -> str:
    """How the user asked for ``requested`` threads, as they wrote it: ``threads=N`` where the setting gave it, else
    ``OMP_NUM_THREADS=N`` (``requested_threads``)."""
    return f"threads={setting}" if setting is not None else f"{THREADS_VARIABLE}={requested}"


def threads_line(threads: int, requested: int | None, cpus: int, jobs: int, busy_cpus: float | None = None) -> str:
    """The line a run logs at its start of the torch threads it runs with, and why that many.

    >>> threads_line(1, None, 2, 2)
    'torch threads: 1 (auto: 2 CPUs this process may use, 2 jobs at once; threads=N sets it)'
    >>> threads_line(1, None, 2, 1, 1.6)
    'torch threads: 1 (auto: 2 CPUs this process may use, 1.6 of them busy with other processes; threads=N sets it)'
    """
    if requested is not None:
        return f"torch threads: {threads} (asked for: threads or OMP_NUM_THREADS)"
    others = (f"{jobs} jobs at once" if jobs > 1 else
              f"{busy_cpus:.1f} of them busy with other processes" if busy_cpus and busy_cpus >= 0.5 else "1 job at once")
    return f"torch threads: {threads} (auto: {cpus} CPUs this process may use, {others}; threads=N sets it)"


class ThreadChoice(NamedTuple):
    line: str  # ``threads_line``
    busy: str | None  # ``busy_line``
    follows_load: bool  # chosen automatically for one job at a time: ``follow_load`` may change it while it trains
    capped: str | None = None  # a count asked for above the CPUs: the line saying so (``nerfexp.cpus.capped_line``)


def start_threads(setting: int | None, launcher: dict | None) -> ThreadChoice:
    """Look at the machine for ``BUSY_SAMPLE_S``, then set torch's intra-op threads for this run
    (``intra_op_threads``: the ``threads`` setting, else ``OMP_NUM_THREADS``, at most the CPUs this process may use,
    else those CPUs, less those other processes kept busy, over the ``launcher``'s jobs at once): the line saying the
    threads (``threads_line``), ``busy_line``'s, whether the count may follow the machine's load while the run trains
    (an automatic choice for a single job: a multirun's jobs divide the CPUs among themselves, and a number the user
    gave stands), and the line saying that a count asked for was capped at the CPUs (``capped_line``), or None."""
    cpus = available_cpus()
    jobs = parallel_jobs(launcher, cpus)
    requested = requested_threads(setting, dict(os.environ))
    start = sample()
    time.sleep(BUSY_SAMPLE_S)
    end = sample()
    busy = other_load(others_cpu_s(start, end), end.wall_s - start.wall_s)
    threads = intra_op_threads(cpus, jobs, requested, busy or 0.0)
    torch.set_num_threads(threads)
    capped = None if requested is None else capped_line(asked_for(setting, requested), requested, cpus)
    return ThreadChoice(threads_line(threads, requested, cpus, jobs, busy), busy_line(start, end, cpus),
                        requested is None and jobs == 1, capped)


def follow_load(threads: int, cpus: int, start: Sample, end: Sample) -> tuple[int, float] | None:
    """A single run's automatic thread count for what other processes did from ``start`` to ``end`` (two samples
    ``FOLLOW_WINDOW_S`` apart, while it trained): ``intra_op_threads`` of the ``cpus`` it may use less the CPUs the
    others kept busy, with that load, where it differs from ``threads`` (the count now); None where it stays, or
    where the system has no counters.

    >>> follow_load(2, 2, Sample(0.0, 0.0, 0.0), Sample(10.0, 10.0, 22.0))  # a neighbour: 12 of 20 CPU seconds
    (1, 1.2)
    >>> follow_load(1, 2, Sample(0.0, 0.0, 0.0), Sample(10.0, 10.0, 10.5)) # it left: 0.05 of a CPU
    (2, 0.05)
    """
    load = other_load(others_cpu_s(start, end), end.wall_s - start.wall_s)
    if load is None:
        return None
    wanted = intra_op_threads(cpus, 1, None, load)
    return None if wanted == threads else (wanted, load)


def share_record(wall_s: float, cpu_s: float | None, others_s: float | None, cpus: int) -> dict:
    """What ``results.json`` says of the machine a run trained on: ``cpu_time_s`` (its own, beside
    ``train_time_s``, its wall time ``wall_s``), ``other_load`` (``other_load``; null: not measured) and ``cpus``
    (those it could use)."""
    load = other_load(others_s, wall_s)
    return {"cpu_time_s": cpu_s, "other_load": None if load is None or not math.isfinite(load) else load,
            "cpus": cpus}
