"""The commands that read a run back (``nerfexp-eval``, ``-render``, ``-export``, ``-view``) say what a run that did
not finish left them: its status read as what it is (``nerfexp.rundir.state``), a killed run's checkpoint named
with its step, before the checkpoint is used; a finished run's read back without a word."""

import json
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from nerfexp.commands import evaluate, export, render, view
from nerfexp.rundir.layout import LAST_CHECKPOINT, process_start
from tests.helpers import run_nerfexp

# each command stopped right after it has read the run back and said what it is, before its own work
STOPPED_AT = {render: "run_scene", export: "export_box", view: "run_scene"}


def killed_copy(tiny_run: Path, folder: Path) -> tuple[Path, int]:
    """``tiny_run`` as a run killed after its last checkpoint leaves it: no results, and a status that still says
    running for a process of this host that has ended; the run directory and that process's id."""
    run_dir = shutil.copytree(tiny_run, folder, ignore=shutil.ignore_patterns("results.json", "eval.json", "render",
                                                                           "export", "view", "test"))
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    started = process_start(child.pid)
    child.kill()
    child.wait()
    status = json.loads((run_dir / "status.json").read_text())
    status.update(state="running", host=socket.gethostname(), pid=child.pid, process_start=started)
    status.pop("collapse", None)
    (run_dir / "status.json").write_text(json.dumps(status))
    return run_dir, child.pid


def said(prog: str, run_dir: Path, pid: int) -> str:
    return (f"{prog}: warning: the run in {run_dir} was killed before it finished (process {pid} is gone; its "
            f"status.json still says running): {run_dir / LAST_CHECKPOINT} is its model at step 60, not at the end "
            "of its training")


def test_an_evaluation_of_a_killed_run_says_so_and_scores_its_last_checkpoint(tiny_run, tmp_path):
    run_dir, pid = killed_copy(tiny_run, tmp_path / "killed")
    result = run_nerfexp(str(run_dir), cwd=tmp_path, script="nerfexp-eval")
    assert result.returncode == 0, result.stderr[-3000:]
    assert said("nerfexp-eval", run_dir, pid) in result.stderr.splitlines()
    scores = json.loads((run_dir / "eval.json").read_text())
    assert scores["step"] == 60 and f"(step 60); written to {run_dir / 'eval.json'}" in result.stdout


@pytest.mark.parametrize("command", [render, export, view])
def test_every_command_reading_a_killed_run_back_says_so_before_its_work(tiny_run, tmp_path, monkeypatch, capsys,
                                                                         command):
    def work(*args, **kwargs):
        raise AssertionError("the command went on to its work")

    monkeypatch.setattr(command, STOPPED_AT[command], work)
    run_dir, pid = killed_copy(tiny_run, tmp_path / "killed")
    with pytest.raises(AssertionError, match="went on to its work"):
        command.main([str(run_dir), "--port", "0"] if command is view else [str(run_dir)])
    prog = command.build_parser().prog
    assert capsys.readouterr().err.splitlines() == [said(prog, run_dir, pid)]
    # a finished run (tiny_run itself) is read back without a word
    with pytest.raises(AssertionError, match="went on to its work"):
        command.main([str(tiny_run), "--port", "0"] if command is view else [str(tiny_run)])
    assert capsys.readouterr().err == ""


def test_a_run_killed_before_its_first_checkpoint_is_named_as_killed_by_the_commands(tiny_run, tmp_path):
    run_dir, pid = killed_copy(tiny_run, tmp_path / "killed")
    shutil.rmtree(run_dir / "checkpoints")
    with pytest.raises(SystemExit) as exit:
        evaluate.main([str(run_dir)])
    assert exit.value.code == (f"nerfexp-eval: error: {run_dir / LAST_CHECKPOINT} does not exist: the run in {run_dir} "
                               f"has saved no checkpoint; it was killed before it finished (process {pid} is gone; "
                               "its status.json still says running)")
