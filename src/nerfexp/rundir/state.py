"""A run's state as its ``status.json`` says it, read as what it is, by every reader: ``nerfexp``'s claim of a run
directory (``nerfexp.rundir.claim``), ``nerfexp-report``'s listing (``nerfexp.report.runs``) and the commands that
read a run back (``nerfexp-eval``, ``-render``, ``-export``, ``-view``: ``unfinished_line``).

A status that says ``running`` for a process of this host that no longer runs (its pid gone, or now another
process's: ``nerfexp.rundir.layout.process_alive``) is a run ``killed`` before it finished: out of memory, a time
limit, SIGKILL, or a library that aborted the process before nerfexp could record the failure. A run of another host
cannot be looked at from here: it stays ``running``, said as not checked. The other states are the status's own:
``finished``, ``failed`` (with its error).
"""

import socket
from pathlib import Path
from typing import NamedTuple

from nerfexp.reading import UnreadableFile
from nerfexp.rundir.layout import STATUS, process_alive, read_json
from nerfexp.rundir.records import STATUS_FIELDS, record_problem

KILLED = "killed"
ENDED_UNFINISHED = ("failed", KILLED)  # runs that will never finish
DAMAGED = "damaged"  # a status that cannot be read as nerfexp writes it (``read_state``)


class RunState(NamedTuple):
    state: str  # finished, failed, running, killed (``status_state``); damaged (``read_state``)
    detail: str  # in words: the error, the process and its host, what is wrong with the status ("": nothing more)
    here: bool = False  # running in a process of this host, alive: a run that is training now


def status_state(status: dict) -> RunState:
    """The state of the run whose ``status.json`` reads ``status`` (as nerfexp writes it: ``STATUS_FIELDS``, its
    ``state`` present), read as what it is (the module's docstring)."""
    state = status["state"]
    if state != "running":
        return RunState(state, status.get("error", ""))
    host, pid = status.get("host"), status.get("pid")
    if host != socket.gethostname() or pid is None:
        return RunState(state, f"on {host}, process {pid} (not checked)")
    if not process_alive(pid, status.get("process_start")):
        return RunState(KILLED, f"process {pid} is gone; its {STATUS} still says running")
    return RunState(state, f"on {host}, process {pid}", here=True)


def read_state(run_dir: Path) -> RunState | None:
    """The state of the run in ``run_dir``: ``status_state`` of its ``status.json``; None where it has none (a run of
    an earlier nerfexp, or files copied without it); ``DAMAGED``, with the problem, where the file cannot be read as
    nerfexp writes it."""
    try:
        status = read_json(Path(run_dir) / STATUS)
    except UnreadableFile as error:
        return RunState(DAMAGED, error.reason)
    if status is None:
        return None
    if (problem := record_problem(status, STATUS_FIELDS, ("state",))) is not None:
        return RunState(DAMAGED, problem)
    return status_state(status)


def unfinished_words(state: RunState | None) -> str | None:
    """What a run in ``state`` (``read_state``'s) is, said where it did not finish or its status cannot tell: ``was
    killed before it finished (process 4242 is gone; ...)``; None where it finished or has no status.

    >>> unfinished_words(RunState("failed", "DatasetError: ..."))
    'failed before it finished (DatasetError: ...)'
    """
    if state is None or state.state == "finished":
        return None
    said = {KILLED: "was killed before it finished", "failed": "failed before it finished",
            "running": "is still running", DAMAGED: f"may not have finished: its {STATUS} is not as nerfexp writes it"}
    return f"{said[state.state]} ({state.detail})" if state.detail else said[state.state]


def unfinished_line(run_dir: Path, checkpoint: Path, step: int) -> str | None:
    """The line a command that reads back the run in ``run_dir`` says where the run did not finish (``unfinished_words``
    of its ``read_state``): the checkpoint it reads, ``checkpoint``, holds the model at ``step``, not at the end of
    training. None where the run finished or has no status."""
    words = unfinished_words(read_state(run_dir))
    if words is None:
        return None
    return f"the run in {run_dir} {words}: {checkpoint} is its model at step {step}, not at the end of its training"
