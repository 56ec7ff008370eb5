"""Faults at the edge end every command in one line, and leave what was there whole: a full disk (a small
tmpfs), a read-only or an immutable folder, SIGINT while a command writes (nerfexp.commands.console's
one_line_errors, nerfexp.files' atomic writes and WriteError). Where the machine does not permit a mount
or chattr, the test is skipped saying so (tests.helpers)."""

import os
import re
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest
import torch

from nerfexp import manifest
from nerfexp.commands import evaluate, export, report
from nerfexp.files import folder_entries
from nerfexp.report import folder as report_folder
from nerfexp.rundir.layout import REPORT_FILES
from tests.helpers import (
    command,
    crossed_threshold,
    digests,
    fault_at,
    fill_disk,
    immutable,
    make_read_only,
    make_run,
    read_json,
    run_nerfexp,
    small_disk,
    unmount,
)

FULL = "cannot write (No space left on device)"


def temporaries(folder: Path) -> list[str]:
    """The files under ``folder`` that an atomic write fills or moves aside (``.NAME.*.tmp``, ``.NAME.*.old``,
    as ``nerfexp.files`` names them): none is left once it ended, however it ended."""
    return [entry for entry in folder_entries(folder)
            if any(part.startswith(".") and part.endswith((".tmp", ".old")) for part in entry.split("/"))]


@pytest.mark.slow
@pytest.mark.parametrize(("fault", "reason"), [("nearly-full", "No space left on device"),
                                               ("read-only", "Read-only file system")])
def test_a_checkpoint_that_cannot_be_written_ends_the_run_in_one_line_and_the_last_one_stays(
        fault, reason, tiny, tmp_path):
    """After the checkpoint of step 30 the disk fills up but for less than a checkpoint, or checkpoints/
    becomes read-only: the one of step 60 cannot be written (once an 85-line traceback on its temporary
    file, or torch's "unexpected pos")."""
    with small_disk(tmp_path / "disk") as disk:
        run_dir = disk / "run"
        checkpoints = run_dir / "checkpoints"
        if fault == "read-only":  # permitted here? asked before training, so that a skip costs nothing
            (disk / "probe").mkdir()
            make_read_only(disk / "probe")
            unmount(disk / "probe")
        try:
            result = run_nerfexp(*tiny, *fault_at(30, fault, checkpoints if fault == "read-only" else disk),
                                 f"hydra.run.dir={run_dir}", cwd=tmp_path)
        finally:
            unmount(checkpoints)
        assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr[-3000:]
        line = f"nerfexp: error: {checkpoints / 'last.ckpt'}: cannot write ({reason})"
        assert result.stderr.splitlines() == [line]
        status = read_json(run_dir / "status.json")
        assert status["state"] == "failed" and str(checkpoints / "last.ckpt") in status["error"]
        checkpoint = torch.load(checkpoints / "last.ckpt", map_location="cpu", weights_only=True)  # whole
        assert checkpoint["global_step"] == 30
        assert temporaries(run_dir) == []


@pytest.mark.slow
def test_a_disk_full_to_the_last_byte_ends_the_run_in_one_line_that_says_the_status_could_not_be_written(
        tiny, tmp_path):
    """TensorBoard's writer thread meets the full disk first (once its traceback, then the main thread's);
    status.json cannot be rewritten either: the line says so."""
    with small_disk(tmp_path / "disk") as disk:
        run_dir = disk / "run"
        result = run_nerfexp(*tiny, *fault_at(30, "full", disk), f"hydra.run.dir={run_dir}", cwd=tmp_path)
        assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr[-3000:]
        (line,) = result.stderr.splitlines()
        assert line.startswith("nerfexp: error: ") and FULL in line
        assert line.endswith(f"; not recorded in status.json ({run_dir / 'status.json'}: {FULL})")
        assert read_json(run_dir / "status.json")["state"] == "running"  # as written before the fault
        checkpoint = torch.load(run_dir / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
        assert checkpoint["global_step"] == 30
        assert temporaries(run_dir) == []


def test_a_full_disk_ends_an_evaluation_in_one_line_and_the_run_stays_as_it_was(tiny_run, tmp_path):
    with small_disk(tmp_path / "disk") as disk:
        run = disk / "run"
        shutil.copytree(tiny_run, run)
        evaluate.main([str(run)])  # an earlier evaluation: its eval.json stays
        before = digests(run)
        fill_disk(disk / "filler")
        with pytest.raises(SystemExit) as exit:
            evaluate.main([str(run)])
        assert exit.value.code == f"nerfexp-eval: error: {run / 'eval.json'}: {FULL}"
        assert digests(run) == before  # hidden files too: no temporary left


def test_an_immutable_run_directory_ends_an_evaluation_in_one_line(tiny_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    before = digests(run)
    with immutable(run), pytest.raises(SystemExit) as exit:
        evaluate.main([str(run)])
    assert exit.value.code == f"nerfexp-eval: error: {run / 'eval.json'}: cannot write (Operation not permitted)"
    assert digests(run) == before


def test_a_full_disk_ends_an_export_in_one_line_and_the_last_export_stays(tiny_run, tmp_path):
    with small_disk(tmp_path / "disk") as disk:
        run = disk / "run"
        shutil.copytree(tiny_run, run)
        threshold = crossed_threshold(run, 8)  # a mesh on any CPU, on the grids of 16 and 24 cells too
        export.main([str(run), "--resolution", "16", "--threshold", threshold])
        before = digests(run)
        fill_disk(disk / "filler")
        with pytest.raises(SystemExit) as exit:
            export.main([str(run), "--resolution", "24", "--threshold", threshold])
        assert exit.value.code == f"nerfexp-export: error: {run / 'export'}: {FULL}"
        assert digests(run) == before


def test_a_full_disk_ends_a_report_in_one_line_and_the_last_report_stays(tiny_run, tmp_path):
    with small_disk(tmp_path / "disk") as disk:
        out = disk / "report"
        report.main([str(tiny_run), "--out", str(out)])
        before = digests(out)
        fill_disk(disk / "filler")
        with pytest.raises(SystemExit) as exit:
            report.main([str(tiny_run), "--out", str(out)])
        assert exit.value.code == f"nerfexp-report: error: {out / 'report.md'}: {FULL}"
        assert digests(out) == before


def interrupt_inside(monkeypatch, module, name: str, folder: Path, call: int = 1) -> list[list[str]]:
    """Make ``module.name`` send SIGINT to this process after its ``call``-th call returns, as Ctrl-C would
    while the command writes; returns, once it did, the temporaries under ``folder`` at that moment."""
    original, calls, seen = getattr(module, name), [], []

    def interrupting(*args, **kwargs):
        result = original(*args, **kwargs)
        calls.append(None)
        if len(calls) == call:
            seen.append(temporaries(folder))
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)  # the handler raises in this thread at its next instruction
        return result

    monkeypatch.setattr(module, name, interrupting)
    return seen


def test_sigint_while_an_export_writes_is_one_line_and_the_last_export_stays(tiny_run, tmp_path, monkeypatch,
                                                                              capsys):
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    threshold = crossed_threshold(run, 8)  # a mesh on any CPU, on the grids of 16 and 24 cells too
    export.main([str(run), "--resolution", "16", "--threshold", threshold])
    before = digests(run)
    seen = interrupt_inside(monkeypatch, export, "ply_bytes", run, call=2)  # mesh.ply written, points.ply next
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit:
        export.main([str(run), "--resolution", "24", "--threshold", threshold])
    assert len(seen) == 1 and seen[0] and seen[0][0].startswith(".export.")  # inside the write
    assert exit.value.code == 130 and capsys.readouterr().err == "nerfexp-export: stopped (SIGINT)\n"
    assert digests(run) == before


# What write_report calls, in order, from reading the runs to the page: a stop after any leaves the previous report
REPORT_STEPS = ("find_runs", "markdown", "budget_rows", "pareto_png", "view_tiles", "page_html")


@pytest.mark.parametrize("step", REPORT_STEPS)
def test_sigint_at_any_step_of_a_report_is_one_line_and_the_previous_report_stays_whole(tiny_run, tmp_path, monkeypatch,
                                                                                         capsys, step):
    out = tmp_path / "report"
    report.main([str(tiny_run), "--out", str(out), "--views", "0"])
    before = digests(out)
    seen = interrupt_inside(monkeypatch, report_folder, step, out)
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit:
        report.main([str(tiny_run), "--out", str(out), "--views", "1"])  # another report: other pictures, another page
    assert len(seen) == 1
    if step == "view_tiles":  # the pictures' folder filled, the files before it written: all beside their places
        assert {entry.split(".")[1] for entry in seen[0]} >= {"report", "report_images", "pareto"}, seen[0]
    assert exit.value.code == 130 and capsys.readouterr().err.splitlines()[-1] == "nerfexp-report: stopped (SIGINT)"
    assert digests(out) == before  # the previous report, every file of it, and its manifest; no temporary


def test_sigint_while_a_report_moves_into_place_takes_effect_once_it_is_all_there(tiny_run, tmp_path, monkeypatch,
                                                                                  capsys):
    out = tmp_path / "report"
    report.main([str(tiny_run), "--out", str(out), "--views", "0"])
    seen = interrupt_inside(monkeypatch, manifest, "record", out)  # the files moved, their records next
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit:
        report.main([str(tiny_run), "--out", str(out), "--views", "1"])
    assert len(seen) == 1 and exit.value.code == 130
    assert capsys.readouterr().err.splitlines()[-1] == "nerfexp-report: stopped (SIGINT)"
    pictures = manifest.folder_files(out, "report_images")
    assert pictures and all(picture.startswith("report_images/view1/") for picture in pictures)  # the new report's
    assert manifest.unproven(out, [*REPORT_FILES, *pictures]) == []  # each recorded as it is
    named = re.findall(r'<img src="(report_images/[^"]+)"', (out / "report.html").read_text())
    assert named and set(named) <= set(pictures)  # the page names only pictures that are there
    assert temporaries(out) == []


@pytest.mark.slow
def test_sigterm_to_the_nerfexp_report_command_while_it_compares_is_one_line_and_the_previous_report_stays(tmp_path):
    """The console script itself, as a job's time limit stops it: SIGTERM once it says it compares two runs of
    5,001 budgets each (seconds of work; the previous report, of the first 2 budgets, is another)."""
    sweep = tmp_path / "sweep"
    for label, offset in (("a", 0.0), ("b", -0.5)):
        make_run(sweep, label, [f"encoding={label}", "seed=0"],
                 test_budgets=[(i + 1, i + 1.0, 20.0 + offset, 0.8) for i in range(2)])
    report.main([str(sweep), "--reference", "encoding=a"])
    for label, offset in (("a", 0.0), ("b", -0.5)):
        shutil.rmtree(sweep / label)
        make_run(sweep, label, [f"encoding={label}", "seed=0"],
                 test_budgets=[(i + 1, i + 1.0, 20.0 + offset, 0.8) for i in range(5_001)])
    before = digests(sweep)
    argv, env = command("nerfexp-report", str(sweep), "--reference", "encoding=a")
    process = subprocess.Popen(argv, cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                               env=env)
    said = []
    for line in process.stderr:  # its progress, a line as each step begins
        said.append(line.rstrip("\n"))
        if line.startswith("nerfexp-report: comparing"):
            process.send_signal(signal.SIGTERM)
            break
    said += process.communicate(timeout=120)[1].splitlines()
    assert process.returncode == 143 and "Traceback" not in "\n".join(said), said
    assert said == [f"nerfexp-report: reading the runs under {sweep}",
                    "nerfexp-report: comparing 2 variants; runs: 2 (2 finished); 10,002 test budgets",
                    "nerfexp-report: stopped (SIGTERM)"]
    assert digests(sweep) == before


@pytest.mark.slow
def test_sigint_to_the_nerfexp_export_command_while_it_writes_a_large_mesh(tiny_run, tmp_path):
    """The console script itself, as a user stops it: SIGINT once its temporary folder appears (a grid of
    128 steps: a mesh of tens of MB, written for a good part of a second)."""
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    threshold = crossed_threshold(run, 16)  # a mesh on any CPU, on the grid of 128 cells too
    export.main([str(run), "--resolution", "16", "--threshold", threshold])
    before = digests(run)
    argv, env = command("nerfexp-export", str(run), "--resolution", "128", "--threshold", threshold)
    process = subprocess.Popen(argv, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env=env)
    try:
        while process.poll() is None and not temporaries(run):
            time.sleep(0.002)
        process.send_signal(signal.SIGINT)
        _, stderr = process.communicate(timeout=120)
    finally:
        process.kill()
    assert (process.returncode, stderr) == (130, "nerfexp-export: stopped (SIGINT)\n")
    assert digests(run) == before
