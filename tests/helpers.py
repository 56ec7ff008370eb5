"""Helpers shared by the tests: the real config shrunk to run in seconds, and the console scripts run
as a user runs them."""

import argparse
import contextlib
import errno
import hashlib
import importlib
import io
import json
import logging
import os
import random
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import traceback
import warnings
from collections.abc import Callable, Iterator
from importlib.metadata import entry_points
from pathlib import Path

import lightning as L
import numpy as np
import tomllib
import torch
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from omegaconf import open_dict

from nerfexp.commands import export
from nerfexp.geometry.cameras import look_at
from nerfexp.scoring.perceptual import ALEXNET_SHA256

REPO = Path(__file__).parents[1]  # on the console scripts' PYTHONPATH: they can load callbacks from here


def options_of(group: str) -> str:
    """``group``'s options as nerfexp's one-line errors list them: the names of its files in conf/, sorted."""
    return ", ".join(sorted(path.stem for path in (REPO / "conf" / group).glob("*.yaml")))


# Overrides that shrink the default experiment: a tiny network on a small version of the built-in scene
# (hierarchical: a single run refuses scale.n_single, which it would not use; TINY_SINGLE adds it).
TINY = [
    "scale.steps=60", "scale.val_every=30", "scale.batch_rays=256", "scale.depth=2", "scale.width=32",
    "scale.skips=[1]", "scale.view_hidden=16", "scale.n_coarse=16", "scale.n_fine=16",
    "scale.image_size=24", "data.n_train=12", "data.n_val=1", "data.n_test=2", "trainer.enable_progress_bar=false",
]
TINY_SINGLE = "scale.n_single=48"  # hierarchical=false: as many evaluations per ray as 16 + (16 + 16)


def tiny_config(*overrides: str):
    """The real config, shrunk by ``TINY``, with ``overrides`` after it (composed without Hydra's runtime)."""
    with initialize_config_module("nerfexp.conf", version_base=None):
        return compose("config", overrides=[*TINY, *overrides])


def without_overrides(cfg):
    """A copy of the composed config ``cfg`` (with Hydra's section) as if what its overrides chose had come from a
    config file (a sweep's, a preset's defaults list): ``hydra.overrides.task`` empty, the choices kept."""
    cfg = cfg.copy()
    with open_dict(cfg):
        cfg.hydra.overrides.task = []
    return cfg


# HTTPS through a proxy where nothing listens (port 9, discard): a test's command downloads nothing, e.g. AlexNet's
# weights for LPIPS (urllib reads these variables); servers on this machine (the viewer's, the download tests') are
# reached directly
NO_INTERNET = {"https_proxy": "http://127.0.0.1:9", "HTTPS_PROXY": "http://127.0.0.1:9",
               "no_proxy": "127.0.0.1,localhost", "NO_PROXY": "127.0.0.1,localhost"}


def command(script: str, *args: str) -> tuple[list[str], dict]:
    """The command line of a console script and the environment to run it in as a user would, without the
    internet (``NO_INTERNET``)."""
    pythonpath = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))
    env = {**os.environ, "HYDRA_FULL_ERROR": "0", "PYTHONWARNINGS": "ignore", "PYTHONPATH": pythonpath,
           **NO_INTERNET}
    return [str(Path(sys.executable).with_name(script)), *args], env


def run_nerfexp(*args: str, cwd: Path, script: str = "nerfexp", new_process: bool = False
                ) -> subprocess.CompletedProcess:
    """Run a console script as a user would; ``cwd`` receives anything written to relative paths. Its exit
    status, standard output and standard error come back as from a process.

    By default the script's entry point runs in this process (``run_in_this_process``): starting a process
    that trains imports Lightning first, which costs more than a tiny run itself. ``new_process=True`` starts
    a new Python process instead, for what only a process shows: signals, a process that kills itself,
    distributed training and launchers, what a command imports, output to pipes as it happens."""
    if new_process:
        argv, env = command(script, *args)
        return subprocess.run(argv, cwd=cwd, capture_output=True, text=True, env=env, timeout=900)
    return run_in_this_process(script, *args, cwd=cwd)


# Overrides that only a process of its own can run: a callback that kills its process, processes that
# data-parallel training spawns, the launchers' jobs (run_nerfexp's new_process=True)
NEEDS_A_PROCESS = re.compile(r"KillAtStep|trainer=(ddp|slurm)|hydra/launcher=")


def run_in_this_process(script: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    """Call console script ``script``'s entry point with ``args`` in this process, in ``cwd``, as its own
    process would run it (``command``'s environment: Hydra's one-line errors, warnings ignored), and return
    what that process would have: SystemExit's status (its message on standard error, status 1, as Python
    prints it), a traceback and status 1 for any other exception, and what it wrote to stdout and stderr.
    What the command changes of the process is put back afterwards (``isolated``)."""
    assert not NEEDS_A_PROCESS.search(" ".join(args)), f"{args}: run with run_nerfexp(..., new_process=True)"
    main = entry_point(script)
    out, err = (io.TextIOWrapper(io.BytesIO(), encoding="utf-8", write_through=True) for _ in range(2))
    status = 0
    with isolated(cwd, [script, *args]), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        os.environ["HYDRA_FULL_ERROR"] = "0"
        try:
            main() if script == "nerfexp" else main(list(args))  # nerfexp's cli reads sys.argv, as Hydra does
        except SystemExit as end:
            if isinstance(end.code, str):
                print(end.code, file=sys.stderr)
            status = end.code if isinstance(end.code, int) else 0 if end.code is None else 1
        except BaseException:  # noqa: BLE001 -- as an uncaught exception ends a process: its traceback, status 1
            traceback.print_exc()
            status = 1
    return subprocess.CompletedProcess([script, *args], status, out.buffer.getvalue().decode(),
                                       err.buffer.getvalue().decode())


def entry_point(script: str) -> Callable:
    """Console script ``script``'s entry point: as nerfexp was installed, else as this tree's pyproject.toml declares
    it (a script added since the install, which only a new install puts on the PATH)."""
    installed = entry_points(group="console_scripts", name=script)
    if installed:
        (entry,) = installed
        return entry.load()
    module, _, name = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"][script].partition(":")
    return getattr(importlib.import_module(module), name)


def all_loggers() -> list[logging.Logger]:
    """The root logger and every logger made so far (placeholders left out)."""
    return [logging.getLogger(), *(logger for logger in logging.Logger.manager.loggerDict.values()
                                   if isinstance(logger, logging.Logger))]


@contextlib.contextmanager
def isolated(cwd: Path, argv: list[str]) -> Iterator[None]:
    """Inside the block, ``cwd`` is the working directory and ``argv`` sys.argv; afterwards the process's
    state a command may change is as before: the environment, logging's handlers and levels (Hydra
    configures logging for each run, with a file handler in its directory), warnings filters, the
    handlers of SIGINT, SIGTERM and SIGUSR2, threading's excepthook, the random states, torch's global
    settings, and Hydra's global state (a test's own compose API, which the command's Hydra replaces)."""
    saved_argv, saved_env = sys.argv, dict(os.environ)
    saved_loggers = {logger: (list(logger.handlers), logger.level, logger.propagate, logger.disabled)
                     for logger in all_loggers()}
    saved_signals = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGUSR2)}
    saved_hook, saved_torch = threading.excepthook, (torch.get_num_threads(), torch.get_default_dtype(),
                                                     torch.get_float32_matmul_precision(),
                                                     torch.are_deterministic_algorithms_enabled())
    saved_random = (random.getstate(), np.random.get_state(), torch.random.get_rng_state())
    composing = GlobalHydra.instance()  # a test's own compose API (a fixture's initialize_config_module)
    saved_hydra = composing.hydra if composing.is_initialized() else None
    composing.clear()  # the command's @hydra.main initializes it anew
    sys.argv = argv
    try:
        with contextlib.chdir(cwd), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # as PYTHONWARNINGS=ignore does for a command's process
            yield
    finally:
        sys.argv = saved_argv
        composing.clear()
        if saved_hydra is not None:
            composing.initialize(saved_hydra)
        os.environ.clear()
        os.environ.update(saved_env)
        for logger in all_loggers():
            handlers, level, propagate, disabled = saved_loggers.get(logger, ([], logging.NOTSET, True, False))
            for handler in logger.handlers:
                if handler not in handlers:
                    handler.close()  # a run's log file: closed, not written to by later tests
            logger.handlers[:], logger.propagate, logger.disabled = handlers, propagate, disabled
            logger.setLevel(level)  # and the loggers' cached levels cleared
        for signum, handler in saved_signals.items():
            signal.signal(signum, handler)
        threading.excepthook = saved_hook
        threads, dtype, matmul, deterministic = saved_torch
        torch.set_num_threads(threads)
        torch.set_default_dtype(dtype)
        torch.set_float32_matmul_precision(matmul)
        torch.use_deterministic_algorithms(deterministic)
        random.setstate(saved_random[0])
        np.random.set_state(saved_random[1])
        torch.random.set_rng_state(saved_random[2])


def start_nerfexp(*args: str, cwd: Path) -> subprocess.Popen:
    """Start ``nerfexp`` as ``run_nerfexp`` runs it, without waiting for it (stdout and stderr: pipes)."""
    argv, env = command("nerfexp", *args)
    return subprocess.Popen(argv, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def read_json(path: Path) -> dict:
    return json.loads(path.read_text())


def digests(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` (relative path) with the SHA-256 of its bytes: to show nothing changed."""
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


class KillAtStep(L.Callback):
    """Kills its own process with SIGKILL (no clean-up, as a preempted or out-of-memory job dies) when
    training is about to take step ``step + 1``: after the checkpoint and validation of step ``step``.
    Injected from the command line by ``kill_at(step)``."""

    def __init__(self, step: int):
        self.step = step

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.global_step == self.step:
            os.kill(os.getpid(), signal.SIGKILL)


def kill_at(step: int) -> list[str]:
    """Overrides that make a ``nerfexp`` run kill itself after step ``step`` (``KillAtStep``)."""
    return ["+callbacks.kill._target_=tests.helpers.KillAtStep", f"+callbacks.kill.step={step}"]


def mount_or_skip(*argv: str) -> None:
    """Run ``mount ARGV``; the test is skipped, saying why, where this machine does not permit it (not
    root, a container without the capability, no ``mount``)."""
    import pytest

    try:
        done = subprocess.run(["mount", *argv], capture_output=True, text=True)
    except FileNotFoundError:
        pytest.skip("no mount command here: the fault needs a mounted file system")
    if done.returncode != 0:
        pytest.skip(f"mount {' '.join(argv)} is not permitted here ({done.stderr.strip()}): the fault needs it")


def unmount(folder: Path) -> None:
    """Unmount whatever is mounted at ``folder`` (the last mount first), until nothing is."""
    while subprocess.run(["mountpoint", "-q", str(folder)]).returncode == 0:
        subprocess.run(["umount", str(folder)], check=True)


@contextlib.contextmanager
def small_disk(folder: Path, size: str = "64m") -> Iterator[Path]:
    """A tmpfs of ``size`` mounted at ``folder`` (made where missing) for the block, to fill
    (``fill_disk``); unmounted after it, with whatever it holds (``mount_or_skip``)."""
    folder.mkdir(parents=True, exist_ok=True)
    mount_or_skip("-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder))
    try:
        yield folder
    finally:
        unmount(folder)


def fill_disk(filler: Path, leave: int = 0) -> None:
    """Fill the file system of ``filler``'s folder with the file ``filler`` to its last byte, then give
    back ``leave`` bytes of it (a disk nearly full: small files fit, a checkpoint does not)."""
    block = bytes(1 << 20)
    with open(filler, "wb", buffering=0) as file:
        while block:
            try:
                file.write(block)
            except OSError as error:
                if error.errno != errno.ENOSPC:
                    raise
                block = block[:len(block) // 2]
    os.truncate(filler, max(0, filler.stat().st_size - leave))


def make_read_only(folder: Path) -> None:
    """Make ``folder`` a read-only file system: bind-mounted over itself, read-only (as root, a mode
    stops no write); ``unmount`` ends it."""
    mount_or_skip("--bind", str(folder), str(folder))
    mount_or_skip("-o", "remount,bind,ro", str(folder))


@contextlib.contextmanager
def immutable(folder: Path) -> Iterator[Path]:
    """``folder`` immutable (``chattr +i``: nothing in it made, removed or renamed, by root too) for the
    block; the test is skipped, saying why, where its file system or this machine does not permit it."""
    import pytest

    try:
        done = subprocess.run(["chattr", "+i", str(folder)], capture_output=True, text=True)
    except FileNotFoundError:
        pytest.skip("no chattr command here: the fault needs an immutable folder")
    if done.returncode != 0:
        pytest.skip(f"chattr +i {folder} is not permitted here ({done.stderr.strip()}): the fault needs it")
    try:
        yield folder
    finally:
        subprocess.run(["chattr", "-i", str(folder)], check=True)


NEARLY = 64 << 10  # what a nearly full disk has left: less than a checkpoint of the TINY network


class FaultAtStep(L.Callback):
    """Where training is about to take step ``step + 1`` (as ``KillAtStep``), ``fault`` strikes ``folder``:
    ``full`` fills its disk (``fill_disk``, with the file ``folder/filler``), ``nearly-full`` leaves
    ``NEARLY`` bytes of it, ``read-only`` makes it a read-only file system (``make_read_only``; the test
    unmounts it). Injected by ``fault_at``."""

    def __init__(self, step: int, fault: str, folder: str):
        self.step = step
        self.fault = fault
        self.folder = Path(folder)

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.global_step != self.step:
            return
        if self.fault == "read-only":
            make_read_only(self.folder)
        else:
            fill_disk(self.folder / "filler", NEARLY if self.fault == "nearly-full" else 0)


def fault_at(step: int, fault: str, folder: Path) -> list[str]:
    """Overrides that make ``fault`` strike ``folder`` after step ``step`` of a ``nerfexp`` run (``FaultAtStep``)."""
    return ["+callbacks.fault._target_=tests.helpers.FaultAtStep", f"+callbacks.fault.step={step}",
            f"+callbacks.fault.fault={fault}", f"+callbacks.fault.folder={folder}"]


class NanTargets(L.Callback):
    """Makes the target colours of the first training batch NaN (as a damaged image could), so that the
    step's losses are NaN while every setting and weight is finite. Injected by ``nan_targets()``."""

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.global_step == 0:
            batch["rgb"].fill_(float("nan"))


class PacedSteps(L.Callback):
    """Sleeps ``seconds`` after each training step: a run that must last (until a time limit ends it) then
    leaves the machine's cores to the tests running beside it."""

    def __init__(self, seconds: float):
        self.seconds = seconds

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        time.sleep(self.seconds)


def nan_targets() -> list[str]:
    """Overrides that make a ``nerfexp`` run's first batch have NaN targets (``NanTargets``)."""
    return ["+callbacks.nan._target_=tests.helpers.NanTargets"]


def final_state(run_dir: Path) -> dict:
    """What a run's last checkpoint holds: its step, learning rate, weights and Adam state."""
    checkpoint = torch.load(run_dir / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    return {"step": checkpoint["global_step"], "lr": checkpoint["optimizer_states"][0]["param_groups"][0]["lr"],
            "weights": checkpoint["state_dict"], "adam": checkpoint["optimizer_states"][0]["state"]}


def cameras_at(distance: list[float], elevation_deg: list[float], azimuth_deg: list[float]) -> torch.Tensor:
    """Cameras [N, 4, 4] at the given spherical coordinates (z up), looking at the origin."""
    r, e, a = (torch.tensor(v, dtype=torch.float64) for v in (distance, elevation_deg, azimuth_deg))
    e, a = torch.deg2rad(e), torch.deg2rad(a)
    eye = r[:, None] * torch.stack([e.cos() * a.cos(), e.cos() * a.sin(), e.sin()], -1)
    return look_at(eye, torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))


def added_arguments(build_parser: Callable[[], argparse.ArgumentParser]) -> tuple[argparse.ArgumentParser, list]:
    """The parser ``build_parser()`` makes, and the action of every argument added to it, as ``add_argument``
    returns each (argparse has no public list of a parser's arguments)."""
    actions, add = [], argparse.ArgumentParser.add_argument

    def recorded(parser, *args, **kwargs):
        actions.append(add(parser, *args, **kwargs))
        return actions[-1]

    argparse.ArgumentParser.add_argument = recorded
    try:
        parser = build_parser()
    finally:
        argparse.ArgumentParser.add_argument = add
    return parser, actions


def undocumented_arguments(build_parser: Callable[[], argparse.ArgumentParser]) -> list[str]:
    """The arguments of ``build_parser()``'s parser that have no help text (``added_arguments``); every option
    its usage line shows was seen added, so that none escapes the check (one added through a group)."""
    parser, actions = added_arguments(build_parser)
    options = {option for action in actions for option in action.option_strings}
    assert set(re.findall(r"(?<![\w-])--?[A-Za-z][\w-]*", parser.format_usage())) <= options
    return [action.dest for action in actions if not action.help]


def one_error_line(result, prog: str = "nerfexp") -> str:
    """The one ``PROG: error: ...`` line of a command that failed with exit status 1 and no traceback."""
    assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr[-3000:]
    (line,) = [line for line in result.stderr.splitlines() if line.startswith(f"{prog}: error:")]
    return line


def make_run(root: Path, name: str, overrides: list[str], state: str = "finished", psnr: float = 20.0,
             ssim: float = 0.8, time_s: float = 100.0, choices: dict | None = None, pid: int | None = None,
             error: str = "", host: str | None = None, curve=((50.0, 15.0), (100.0, 18.0)),
             precision: str = "32-true", lpips: float | None = None,
             test_budgets: list[tuple[int, float, float, float]] | None = None) -> Path:
    """A run directory ``root/name`` as nerfexp leaves it, with known numbers: its status, its validation
    ``curve`` (wall seconds, PSNR), and where ``state`` is finished its test scores and results.json (with
    ``lpips`` its test LPIPS too, as a run that scored it with the published weights, whose SHA-256 it records;
    without, none, as one that did not). ``test_budgets``: (step, training seconds, test PSNR, test SSIM) of each
    budget, the last the end (its step, time and scores the run's ``steps``, ``train_time_s`` and test scores, in
    place of ``time_s``, ``psnr`` and ``ssim``); without, none (as an earlier nerfexp's run, of 20 steps)."""
    steps = 20
    if test_budgets is not None:
        steps, time_s, psnr, ssim = test_budgets[-1]
    run = root / name
    run.mkdir(parents=True)
    status = {"state": state, "overrides": overrides, "host": host or socket.gethostname(),
              "pid": pid or os.getpid(), "time_unix": 0.0}
    if error:
        status["error"] = error
    (run / "status.json").write_text(json.dumps(status))
    lines = [{"step": 10 * (i + 1), "wall_time_s": t, "split": "val", "psnr": p, "ssim": 0.5}
             for i, (t, p) in enumerate(curve)]
    if state == "finished":
        lines += [{"step": step, "wall_time_s": seconds, "split": "test", "psnr": p, "ssim": s}
                  for step, seconds, p, s in (test_budgets or [])[:-1]]
        lines.append({"step": steps, "wall_time_s": time_s, "split": "test", "psnr": psnr, "ssim": ssim,
                      **({} if lpips is None else {"lpips": lpips})})
        results = {"test_psnr": psnr, "test_ssim": ssim, "val_psnr": curve[-1][1], "train_time_s": time_s,
                   "steps": steps, "time_per_step_s": time_s / steps, "rays_per_s": 256 * steps / time_s,
                   "batch_rays": 256, "n_params": 1000, "evaluations_per_ray": 96,
                   "machine": {"host": host or "lab-pc", "device": "CPU (2 cores, 2 torch threads)"},
                   "choices": choices or {}, "overrides": overrides, "precision": precision,
                   **({} if lpips is None else {"test_lpips": lpips, "lpips_weights_sha256": ALEXNET_SHA256})}
        if test_budgets is not None:
            results["test_budgets"] = [{"step": step, "train_time_s": seconds, "evaluations": 96.0 * 256 * step,
                                        "test_psnr": p, "test_ssim": s, "score_s": 0.5}
                                       for step, seconds, p, s in test_budgets]
            results["budget_scoring_s"] = 0.5 * (len(test_budgets) - 1)
        (run / "results.json").write_text(json.dumps(results))
    (run / "metrics.jsonl").write_text("".join(json.dumps(line) + "\n" for line in lines))
    return run


PLY_DTYPES = {"char": "i1", "uchar": "u1", "short": "<i2", "ushort": "<u2", "int": "<i4", "uint": "<u4",
              "float": "<f4", "double": "<f8"}  # the PLY specification's types, little-endian


def read_ply(data: bytes) -> tuple[list[str], dict[str, np.ndarray]]:
    """``(comments, elements)`` of a binary little-endian PLY file: each element a structured array [N] with
    one field per property (a list property: the field ``NAME`` of its values and ``NAME count``, every
    row's count asserted equal to the first row's, as in a triangle mesh). The file must end where its
    last element does."""
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:end].decode("ascii").splitlines()
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"] and lines[-1] == "end_header", lines
    comments = [line[len("comment "):] for line in lines if line.startswith("comment ")]
    layout = []  # (element name, count, [property words])
    for line in lines[2:-1]:
        words = line.split()
        if words[0] == "element":
            layout.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            layout[-1][2].append(words[1:])
        else:
            assert words[0] == "comment", line
    elements, offset = {}, end
    for name, count, properties in layout:
        fields = []
        for words in properties:
            if words[0] == "list":  # list COUNT_TYPE VALUE_TYPE NAME: the first row's count is every row's
                _, count_type, value_type, field = words
                before = np.dtype(fields).itemsize if fields else 0  # bytes of the row before the count
                length = int(np.frombuffer(data, PLY_DTYPES[count_type], 1, offset + before)[0]) if count else 1
                fields += [(f"{field} count", PLY_DTYPES[count_type]), (field, PLY_DTYPES[value_type], (length,))]
            else:
                fields.append((words[1], PLY_DTYPES[words[0]]))
        dtype = np.dtype(fields)
        rows = np.frombuffer(data, dtype, count, offset) if count else np.zeros(0, dtype)
        for field in dtype.names:
            if field.endswith(" count"):
                assert (rows[field] == dtype[field[:-len(" count")]].shape[0]).all(), field
        elements[name] = rows
        offset += count * dtype.itemsize
    assert offset == len(data), f"{len(data) - offset} bytes after the last element"
    return comments, elements


# nerfexp-export's line for a given threshold that no density on its grid crosses: the densities' range, to 4 digits
NO_SURFACE = re.compile(r"no surface at --threshold \S+: the field's densities on the \d+ x \d+ x \d+ grid over the "
                        r"box .* lie in \[(\S+), (\S+)\]; choose a threshold between them$")


def threshold_between(message: str) -> float:
    """A threshold half-way between the densities that nerfexp-export's ``NO_SURFACE`` line ``message`` gives, as the
    line advises: one that the field crosses on that grid."""
    match = NO_SURFACE.search(message)
    assert match, message
    low, high = (float(v) for v in match.groups())
    assert low < high, message  # a grid of one density (to 4 digits) has no surface to find
    return (low + high) / 2


def crossed_threshold(run: Path, resolution: int) -> str:
    """A ``--threshold`` that the field of the run at ``run`` crosses on nerfexp-export's grid of ``resolution``
    cells (``threshold_between`` the densities that an export refused for its largest threshold names), and so on
    every grid holding that one's points (over a cube, such as the tiny run's box: a multiple of ``resolution``
    cells). For a test that needs a mesh of a briefly trained run and is not about the default threshold: where such
    a field's default falls against a coarse grid's densities depends on the CPU that trained it
    (``trainer.precision=auto`` trains in bf16 where the CPU has bf16 units and a step measured faster in it, in
    float32 elsewhere)."""
    try:
        export.main([str(run), "--resolution", f"{resolution}", "--threshold", f"{export.DENSITY_LIMIT!r}"])
    except SystemExit as refused:
        return f"{threshold_between(str(refused.code))}"
    raise AssertionError(f"nerfexp-export {run} found a surface at --threshold {export.DENSITY_LIMIT!r}")
