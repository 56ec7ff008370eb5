"""What the commands print: help that explains nerfexp, a run's own lines and nothing else, progress in
steps, and a log redirected to a file that shows each line when it happens."""

import ast
import errno
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time

import lightning as L
import pytest
import torch
from torch.utils.data import DataLoader, IterableDataset

from nerfexp.commands import data, evaluate, render, report, scene, view
from nerfexp.commands.console import one_line_errors
from nerfexp.files import WriteError
from nerfexp.training.progress import StepProgressBar
from tests.helpers import REPO, TINY, command, run_nerfexp, undocumented_arguments

OWN_LINE = re.compile(r"\[\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}\]\[nerfexp[.\w]*\]\[INFO\] - ")  # nerfexp's log format
BUSY_LINE = re.compile(r"\[\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}\]\[nerfexp\]\[WARNING\] - ")


def test_nerfexp_help_says_what_it_is_its_groups_sweeps_other_commands_and_outputs(tmp_path):
    done = run_nerfexp("--help", cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    text = done.stdout
    assert text.startswith("nerfexp: experiments and ablations for Neural Radiance Fields")
    assert "powered by Hydra" not in text and "_target_" not in text  # neither Hydra's header nor a config dump
    groups = {line.split(": ")[0]: line.split(": ")[1].split(", ") for line in text.splitlines()
              if re.fullmatch(r"\w+: [\w, ]+", line)}
    for folder in (REPO / "conf").iterdir():  # each group with every option its folder holds
        if folder.is_dir() and folder.name not in ("hydra", "__pycache__"):
            assert groups[folder.name] == sorted(p.stem for p in folder.glob("*.yaml")), folder.name
    assert "+sweeps=NAME" in text and "nerfexp -m " in text
    for other in ("nerfexp-report", "nerfexp-eval", "nerfexp-render", "nerfexp-scene", "nerfexp-export",
                  "nerfexp-view", "nerfexp-data"):
        assert f"  {other} " in text
    assert "outputs/DATE/TIME/" in text and "multirun/DATE/TIME/N/" in text


@pytest.mark.parametrize("module", [data, evaluate, render, report, scene, view], ids=lambda m: m.__name__)
def test_every_commands_help_reads_cleanly(module):
    parser = module.build_parser()
    text = parser.format_help()
    assert parser.description and "``" not in text
    assert undocumented_arguments(module.build_parser) == []


def test_a_run_prints_its_own_lines_only(tmp_path):
    """Warnings on (the tests' helpers turn them off), standard output a pipe as in a SLURM log: no
    Lightning notices, no model summary, no dependency warning; one line per test budget, per validation and the
    result."""
    argv, env = command("nerfexp", *[o for o in TINY if "progress_bar" not in o], f"hydra.run.dir={tmp_path / 'run'}")
    del env["PYTHONWARNINGS"]
    done = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, env=env, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    lines = (done.stdout + done.stderr).splitlines()
    # the one warning a run may give here is its own about the machine: another test may be keeping a CPU busy
    lines = [line for line in lines if not (BUSY_LINE.match(line) and "the machine is already busy" in line)]
    assert [line for line in lines if not OWN_LINE.match(line)] == []
    assert re.search(r"torch threads: \d+ \(.+\)$", lines[0])  # the threads it runs with
    assert re.search(r"trainer.precision=auto: (bf16-mixed|32-true) \(.+\)$", lines[1])  # then, with them, the precision
    assert "LPIPS not scored: " in lines[2]  # TINY's images are below AlexNet's 31 pixels, and its weights absent
    # a line per test budget (the default 1/4 and 1/2: steps 15 and 30) and per validation
    assert [re.search(r"step \d+/60: (validation|test)", line)[0] for line in lines[3:-1]] == [
        "step 15/60: test", "step 30/60: test", "step 30/60: validation", "step 60/60: validation"]
    assert re.search(r"step 15/60: test PSNR \d+\.\d\d dB, SSIM \d\.\d{4} at a budget of 1/4 \(\d+\.\d\d s of scoring, "
                     r"outside the training clock\)$", lines[3])
    assert "test PSNR" in lines[-1]


def test_a_log_redirected_to_a_file_shows_each_validation_as_it_happens(tmp_path):
    """A block-buffered standard output would hold the first validation lines (8 KB of them) until far
    later: the file must have the first one while no more than two others have happened."""
    log = tmp_path / "run.log"
    overrides = [*TINY, "scale.steps=100000", "scale.val_every=5", f"hydra.run.dir={tmp_path / 'run'}"]
    argv, env = command("nerfexp", *overrides)
    with open(log, "w") as out:
        process = subprocess.Popen(argv, cwd=tmp_path, stdout=out, stderr=subprocess.STDOUT, env=env)
        try:
            deadline = time.monotonic() + 300
            while "validation PSNR" not in log.read_text():
                assert process.poll() is None and time.monotonic() < deadline, log.read_text()[-2000:]
                time.sleep(0.2)
            assert log.read_text().count("validation PSNR") <= 3
        finally:
            process.terminate()
            process.wait(timeout=120)


class Endless(IterableDataset):
    def __iter__(self):
        generator = torch.Generator().manual_seed(0)
        while True:
            x = torch.randn(8, 2, generator=generator)
            yield x, x.sum(-1, keepdim=True)


class Regression(L.LightningModule):
    def __init__(self):
        super().__init__()
        self.layer = torch.nn.Linear(2, 1)

    def training_step(self, batch, batch_idx):
        loss = torch.nn.functional.mse_loss(self.layer(batch[0]), batch[1])
        self.log("train/loss", loss, prog_bar=True)
        return loss

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


def test_the_training_bar_counts_the_runs_steps(tmp_path, capsys):
    trainer = L.Trainer(max_steps=7, logger=False, enable_checkpointing=False, enable_model_summary=False,
                        callbacks=[StepProgressBar(enabled=True)], default_root_dir=tmp_path)
    trainer.fit(Regression(), DataLoader(Endless(), batch_size=None))
    out = capsys.readouterr().out
    final = out.split("\r")[-1]
    assert final.startswith("training: 100%") and "7/7" in final and "step/s" in final and "train/loss=" in final
    assert "Epoch" not in out and "v_num" not in out


def test_the_training_bar_is_off_where_output_is_not_a_terminal(capsys):
    assert StepProgressBar().is_disabled  # capsys replaces standard output with a capture: not a terminal
    assert StepProgressBar(enabled=True).is_enabled


@pytest.mark.slow
def test_a_piped_evaluation_draws_no_progress_bar(tiny_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    # bars on, as in the default config (the tiny config turns them off); stdout and stderr are pipes here
    result = run_nerfexp(str(run), "trainer.enable_progress_bar=true", cwd=tmp_path, script="nerfexp-eval",
                         new_process=True)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "test PSNR" in result.stdout
    for stream in (result.stdout, result.stderr):
        assert "\r" not in stream and "Testing" not in stream and "it/s" not in stream, stream[-2000:]


def tqdm_calls(path):
    """Every call of ``tqdm(...)`` in the source file ``path``."""
    return [node for node in ast.walk(ast.parse(path.read_text())) if isinstance(node, ast.Call)
            and (node.func.id if isinstance(node.func, ast.Name) else getattr(node.func, "attr", "")) == "tqdm"]


def test_every_tqdm_bar_is_off_where_its_stream_is_not_a_terminal():
    # tqdm's disable=None turns a bar off where its stream (standard error) is not a terminal
    calls = {path: tqdm_calls(path) for path in (REPO / "src" / "nerfexp").rglob("*.py")}
    assert sum(map(len, calls.values())) >= 10  # the bars of render, export, the loaders, COLMAP and video
    for path, found in calls.items():
        for call in found:
            disable = [k.value for k in call.keywords if k.arg == "disable"]
            assert len(disable) == 1 and isinstance(disable[0], ast.Constant) and disable[0].value is None, \
                f"{path.relative_to(REPO)}:{call.lineno}: a tqdm bar without disable=None"


@pytest.mark.parametrize(("error", "line"), [
    (WriteError(errno.ENOSPC, "No space left on device", "/runs/a/eval.json"),
     "/runs/a/eval.json: cannot write (No space left on device)"),
    (OSError(errno.EROFS, "Read-only file system", "/runs/a/metrics.jsonl"),  # only a write meets it
     "/runs/a/metrics.jsonl: cannot write (Read-only file system)"),
    (OSError(errno.ENOSPC, "No space left on device"), "cannot write (No space left on device)"),
    (PermissionError(errno.EACCES, "Permission denied", "/runs/a/status.json"),
     "/runs/a/status.json: Permission denied"),
    (OSError("/runs/a/metrics.jsonl: wrote 3 of the 90 bytes of a metrics line"),
     "/runs/a/metrics.jsonl: wrote 3 of the 90 bytes of a metrics line"),
])
def test_a_file_that_cannot_be_written_or_read_ends_a_command_in_one_line_naming_it(error, line, capsys):
    with pytest.raises(SystemExit) as exit, one_line_errors("nerfexp-eval"):
        raise error
    assert exit.value.code == f"nerfexp-eval: error: {line}"


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_ends_a_command_in_one_line_with_128_plus_it(signum, capsys):
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    with pytest.raises(SystemExit) as exit, one_line_errors("nerfexp-report"):
        try:
            os.kill(os.getpid(), signum)
            time.sleep(5)  # the handler raises in this thread at its next instruction
        except KeyboardInterrupt:  # as Lightning's does (SIGINT inside fit or test): it exits with 1
            sys.exit(1)
    assert exit.value.code == 128 + signum
    assert capsys.readouterr().err == f"nerfexp-report: stopped ({signal.Signals(signum).name})\n"
    assert {s: signal.getsignal(s) for s in before} == before


def test_a_background_threads_file_error_is_said_once_in_one_line(capsys):
    """As TensorBoard's event writer on a full disk: its thread dies, and the next write in the main thread
    raises the same error; a thread's error that nothing raises again is a warning after the command."""
    full = OSError(errno.ENOSPC, "No space left on device")
    before = threading.excepthook

    def writer():
        raise full

    with pytest.raises(SystemExit) as exit, one_line_errors("nerfexp"):
        thread = threading.Thread(target=writer)
        thread.start()
        thread.join()
        raise full  # the owner of the thread, at its next write
    assert exit.value.code == "nerfexp: error: cannot write (No space left on device)"
    assert capsys.readouterr().err == ""  # no traceback of the thread, no second line
    with one_line_errors("nerfexp"):
        thread = threading.Thread(target=writer)
        thread.start()
        thread.join()
    stopped = "nerfexp: warning: a background thread stopped: cannot write (No space left on device)\n"
    assert capsys.readouterr().err == stopped
    assert threading.excepthook is before
