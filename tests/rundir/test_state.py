"""A run's status read as what it is (``nerfexp.rundir.state``), by every reader alike: a status that says running
for a process of this host that is gone, or whose pid another process now holds, is a killed run for the claim of
a directory, the report's listing and the commands that read a run back; one of another host is not checked."""

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from nerfexp import manifest
from nerfexp.errors import NerfexpError
from nerfexp.report.runs import read_run
from nerfexp.rundir.claim import admit_run, ended_unfinished, held_run
from nerfexp.rundir.layout import LAST_CHECKPOINT, RUN_CONFIG, process_start
from nerfexp.rundir.state import RunState, read_state, status_state, unfinished_line, unfinished_words
from nerfexp.rundir.trained import find_run

HOST = socket.gethostname()


@pytest.fixture(scope="module")
def ended() -> tuple[int, int]:
    """(pid, start) of a process that ran and has ended, as a job killed by the system leaves them."""
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    started = process_start(child.pid)
    child.kill()
    child.wait()
    return child.pid, started


def statuses(ended: tuple[int, int]) -> dict[str, tuple[dict, RunState]]:
    """Statuses as nerfexp writes them, each with the state it is (worked out by hand from how it was made)."""
    pid, started = ended
    me, my_start = os.getpid(), process_start(os.getpid())
    running = {"state": "running", "overrides": ["seed=0"], "host": HOST}
    return {
        "finished": ({"state": "finished", "overrides": ["seed=0"], "host": HOST, "pid": pid},
                     RunState("finished", "")),
        "failed": ({"state": "failed", "overrides": ["seed=0"], "host": HOST, "pid": pid, "error": "OSError: full"},
                   RunState("failed", "OSError: full")),
        "running here": ({**running, "pid": me, "process_start": my_start},
                         RunState("running", f"on {HOST}, process {me}", here=True)),
        "running, start not recorded": ({**running, "pid": me}, RunState("running", f"on {HOST}, process {me}",
                                                                          here=True)),
        "killed": ({**running, "pid": pid, "process_start": started},
                   RunState("killed", f"process {pid} is gone; its status.json still says running")),
        "killed, start not recorded": ({**running, "pid": pid}, RunState(
            "killed", f"process {pid} is gone; its status.json still says running")),
        # the pid is alive, but another process started then: the run's own is gone
        "killed, pid reused": ({**running, "pid": me, "process_start": my_start + 1},
                               RunState("killed", f"process {me} is gone; its status.json still says running")),
        "running elsewhere": ({**running, "host": "another-node", "pid": pid},
                              RunState("running", f"on another-node, process {pid} (not checked)")),
    }


CASES = ["finished", "failed", "running here", "running, start not recorded", "killed", "killed, start not recorded",
         "killed, pid reused", "running elsewhere"]


@pytest.mark.parametrize("case", CASES)
def test_a_status_is_read_as_the_state_its_process_shows(ended, case):
    status, state = statuses(ended)[case]
    assert status_state(status) == state


def run_with(folder: Path, status: dict | None) -> Path:
    """A run directory as a run leaves it before its first checkpoint (its config, log and ``status``), its files
    recorded in its manifest."""
    (folder / RUN_CONFIG).parent.mkdir(parents=True)
    (folder / RUN_CONFIG).write_text("seed: 0\n")
    (folder / "nerfexp.log").write_text("")
    names = [RUN_CONFIG.as_posix(), "nerfexp.log"]
    if status is not None:
        (folder / "status.json").write_text(json.dumps(status))
        names.append("status.json")
    manifest.record(folder, names)
    return folder


@pytest.mark.parametrize("case", [case for case in CASES if case != "finished"])
def test_every_reader_of_a_status_reads_the_state_it_is(ended, tmp_path, case):
    status, state = statuses(ended)[case]
    run_dir = run_with(tmp_path / "run", status)
    assert read_state(run_dir) == state
    # the report's listing
    listed = read_run(run_dir)
    assert (listed.state, listed.detail) == state[:2]
    # the claim of the directory: a run that will never finish, and saved no checkpoint, is replaced; one that may
    # still run is not, and either is named by its state
    assert held_run(run_dir) == f"a {state.state} run (seed=0)"
    assert ended_unfinished(run_dir) == (state.state in ("failed", "killed"))
    if ended_unfinished(run_dir):
        assert admit_run(run_dir, None) == [".hydra/config.yaml", "nerfexp.log", "status.json"]
    else:
        with pytest.raises(NerfexpError, match="holds a running run \\(seed=0\\): choose another directory"):
            admit_run(run_dir, None)
    # the commands that read a run back: a run with no checkpoint says how it ended; one with a checkpoint is read,
    # with a line saying what the checkpoint holds
    with pytest.raises(NerfexpError) as error:
        find_run(run_dir)
    assert str(error.value) == (f"{run_dir / LAST_CHECKPOINT} does not exist: the run in {run_dir} has saved no "
                                f"checkpoint; it {unfinished_words(state)}")
    said = {"failed": "failed before it finished (OSError: full)",
            "killed": f"was killed before it finished ({state.detail})",
            "running": f"is still running ({state.detail})"}[state.state]
    assert unfinished_line(run_dir, run_dir / LAST_CHECKPOINT, 30) == (
        f"the run in {run_dir} {said}: {run_dir / LAST_CHECKPOINT} is its model at step 30, not at the end of its "
        "training")
    if state.state == "killed":  # its checkpoint is the run's to continue, named in the refusal as a killed run's
        (run_dir / LAST_CHECKPOINT).parent.mkdir()
        (run_dir / LAST_CHECKPOINT).write_bytes(b"")
        with pytest.raises(NerfexpError, match="holds a killed run \\(seed=0\\): continue it with resume="):
            admit_run(run_dir, None)
        assert admit_run(run_dir, str(run_dir / LAST_CHECKPOINT)) is None  # resume=: continued in its directory


def test_a_finished_run_or_one_without_a_status_is_read_back_without_a_word(ended, tmp_path):
    finished = run_with(tmp_path / "finished", statuses(ended)["finished"][0])
    bare = run_with(tmp_path / "bare", None)  # an earlier nerfexp's run, or a run's files copied without it
    for run_dir in (finished, bare):
        assert unfinished_line(run_dir, run_dir / LAST_CHECKPOINT, 60) is None
    assert read_state(bare) is None and read_state(finished) == RunState("finished", "")


@pytest.mark.parametrize(("text", "problem"), [
    ('{"state": "running", "pid": "4242"}', "key 'pid' is '4242': expected a whole number in [1, 2147483647]"),
    ('{"state": "paused"}', "key 'state' is 'paused': expected one of running, finished, failed"),
    ('{"state": "running"', "not JSON"),
])
def test_a_status_that_is_not_as_nerfexp_writes_it_says_the_run_may_not_have_finished(tmp_path, text, problem):
    run_dir = run_with(tmp_path / "run", None)
    (run_dir / "status.json").write_text(text)
    state = read_state(run_dir)
    assert state.state == "damaged" and problem in state.detail
    assert unfinished_line(run_dir, run_dir / LAST_CHECKPOINT, 7).startswith(
        f"the run in {run_dir} may not have finished: its status.json is not as nerfexp writes it (")


def test_a_run_training_now_on_this_host_is_not_continued_in_its_own_directory(ended, tmp_path):
    # two processes would write one directory: refused until it ends; one of another host cannot be checked, and a
    # run there killed outright (SIGKILL, out of memory) is continued where its status was left saying running
    here = run_with(tmp_path / "here", statuses(ended)["running here"][0])
    (here / LAST_CHECKPOINT).parent.mkdir()
    (here / LAST_CHECKPOINT).write_bytes(b"")
    with pytest.raises(NerfexpError) as error:
        admit_run(here, str(here / LAST_CHECKPOINT))
    assert str(error.value) == (
        f"{here} holds a running run (seed=0), still training (on {HOST}, process {os.getpid()}): continuing it there "
        f"while it runs would have two runs write one directory; wait for it to end, or stop it, then "
        f"resume={here / LAST_CHECKPOINT} hydra.run.dir={here}")
    elsewhere = run_with(tmp_path / "elsewhere", statuses(ended)["running elsewhere"][0])
    (elsewhere / LAST_CHECKPOINT).parent.mkdir()
    (elsewhere / LAST_CHECKPOINT).write_bytes(b"")
    assert admit_run(elsewhere, str(elsewhere / LAST_CHECKPOINT)) is None
