"""The run directory's layout: the names of the files a run leaves, its status and records, written
atomically and read back, and how runs are found under a folder (the package's docstring lists them)."""

import contextlib
import json
import math
import os
import re
import socket
import time
from pathlib import Path

import torch
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import ChoiceSweep, RangeSweep
from hydra.errors import HydraException

from nerfexp import manifest, reading
from nerfexp.files import writing
from nerfexp.reading import sha256

STATUS = "status.json"
RESULTS = "results.json"
METRICS = "metrics.jsonl"
EVAL = "eval.json"
TEST_DIR = "test"
RENDER_DIR = "render"
EXPORT_DIR = "export"
CAMERA_PATH = Path("view", "camera_path.json")  # nerfexp-view's saved camera path
RUN_CONFIG = Path(".hydra", "config.yaml")  # the composed config, as Hydra saves it in every run directory
LAST_CHECKPOINT = Path("checkpoints", "last.ckpt")
# the training cameras as camera refinement (camera_opt) left them, with their errors where the truth is known
REFINED_POSES = Path("cameras", "train_poses.json")
# what nerfexp-report writes into its folder (a sweep's or a run's, by default): its pages, its plots, and the
# folder of the page's pictures (the only place these names are spelled)
REPORT_MD, REPORT_CSV, REPORT_HTML = "report.md", "report.csv", "report.html"
REPORT_BUDGETS_CSV = "report_budgets.csv"
PSNR_PLOT, PARETO_PLOT, DIFFERENCE_PLOT = "psnr_vs_time.png", "pareto.png", "difference_vs_time.png"
REPORT_IMAGES = "report_images"
REPORT_FILES = (REPORT_MD, REPORT_CSV, REPORT_BUDGETS_CSV, REPORT_HTML, PSNR_PLOT, PARETO_PLOT,
                DIFFERENCE_PLOT)  # and the folder REPORT_IMAGES
# What a run's libraries and guards write into its directory under names nerfexp gives them (``nerfexp.files.
# is_made`` patterns; the run's log, ``hydra.job.name``.log, aside): Hydra's config, the checkpoints, the
# guards' debug files, each logger's (conf/logger/, and the images of a logger without a folder of its own).
# nerfexp records them in the run's manifest (``nerfexp.manifest``) at points it controls: Hydra's config when
# the job starts, all of them when it ends, finished or failed (``nerfexp.commands.train.main``).
RUN_LIBRARY_FILES = (RUN_CONFIG.parent.name, LAST_CHECKPOINT.parent.name, "debug", "tensorboard", "csv", "wandb",
                     "mlflow.db*", "mlartifacts", "images")
# what a resumed run writes over in its directory: its own, by the manifest, or the resume is refused
RUN_REWRITES = (STATUS, RESULTS, METRICS, RUN_CONFIG.parent.name, TEST_DIR, REFINED_POSES.parent.name)

# Where the classes of a run's config lived before the package was split into layers (and the data group


def is_global_zero() -> bool:
    """Whether this process is global rank 0, the one that writes a run's files: always in a run of one
    process; known before any trainer exists from the environment a launcher sets (``RANK``,
    ``LOCAL_RANK``, ``SLURM_PROCID``), and kept up to date by Lightning's strategies (imported here, not
    at the top: a command that stops at a bad setting need not wait for Lightning, docs/testing.md)."""
    from lightning.pytorch.utilities.rank_zero import rank_zero_only
    return rank_zero_only.rank == 0


def process_start(pid: int) -> int | None:
    """When process ``pid`` started, in clock ticks after the machine booted (field 22 of Linux's
    ``/proc/PID/stat``): with the pid it identifies a process, since the system reuses pids. None where
    no such process runs, or the system has no ``/proc``."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return int(stat.rsplit(")", 1)[1].split()[19])  # fields from the third on follow the command's ")"


def process_alive(pid: int, started: int | None) -> bool:
    """Whether the process ``pid`` that started at ``started`` (``process_start``; None: not recorded)
    still runs on this host. A pid that now belongs to a process started at another time is not it."""
    try:
        with contextlib.suppress(PermissionError):  # another user's process: the pid is taken
            os.kill(pid, 0)
    except ProcessLookupError:
        return False
    now = process_start(pid)
    return started is None or now is None or now == started


def status_bytes(state: str, overrides: list[str], **details) -> bytes:
    """A ``status.json``: the run's ``state`` (running, finished, failed) with this host, process id (and
    start, see ``process_start``), the time and ``details``."""
    pid = os.getpid()
    record = {"state": state, "overrides": list(overrides), "host": socket.gethostname(), "pid": pid,
              "process_start": process_start(pid), "time_unix": time.time(), **details}
    return json.dumps(record, indent=2).encode()


def write_status(output_dir: str | Path, state: str, overrides: list[str], **details) -> None:
    """Record a run's ``state`` in its ``status.json`` (``status_bytes``), replacing the last one (and in its
    manifest, ``nerfexp.manifest``)."""
    manifest.write(output_dir, STATUS, status_bytes(state, overrides, **details))


def write_json(path: Path, record: dict) -> None:
    """A run's JSON file (results, evaluation) at the top of its directory, indented, written atomically and
    recorded in the directory's manifest."""
    manifest.write(path.parent, path.name, json.dumps(record, indent=2).encode())


def read_json(path: Path) -> object:
    """The JSON file ``path`` (a run's record, read bounded: ``nerfexp.reading.read_json``, whose
    ``UnreadableFile`` names the file); None where it does not exist."""
    return reading.read_json(path) if os.path.lexists(path) else None


def append_metrics(output_dir: str | Path, record: dict) -> None:
    """Add one evaluation's ``record`` as a line of the run's ``metrics.jsonl``: one ``write`` of the
    whole line to the file opened for appending, which the kernel places at the end of the file as one
    piece, so the lines of several processes never overwrite or cut into each other."""
    path = Path(output_dir) / METRICS
    path.parent.mkdir(parents=True, exist_ok=True)
    line = (json.dumps(record) + "\n").encode()
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        with writing(path):  # a full disk: an error naming the file
            written = os.write(fd, line)
    finally:
        os.close(fd)
    if written != len(line):  # a full disk: say so rather than leave a line that reads as another
        raise OSError(f"{path}: wrote {written} of the {len(line)} bytes of a metrics line")
    manifest.record(output_dir, [METRICS])  # after each line: the file as it is now is the run's


def read_metrics(run_dir: Path, ended: bool = False) -> list[dict]:
    """The records of a run's ``metrics.jsonl``, in order; none where it has none. A last line without
    its newline is one still being written where the run may still run: left out; where the run has
    ``ended`` (finished, failed or killed) nothing will finish it, so it was cut: a ValueError naming it,
    as is a line that is not JSON."""
    path = Path(run_dir) / METRICS
    try:
        lines = reading.read_text(path, reading.RECORD_BYTES).split("\n") if os.path.lexists(path) else [""]
    except reading.UnreadableFile as error:
        raise ValueError(error.reason) from None
    if ended and lines[-1]:
        raise ValueError(f"line {len(lines)}, the last, is cut (no newline, and the run has ended)")
    records = []
    for number, line in enumerate(lines[:-1], 1):
        try:
            records.append(reading.parse_json(line, f"line {number}"))
        except reading.UnreadableFile as error:
            raise ValueError(f"line {number} is {error.reason}") from None
    return records


def find_run_dirs(directory: Path) -> set[Path]:
    """Every run directory under ``directory`` (itself included): a folder holding ``status.json`` or
    ``results.json``."""
    return {p.parent for name in (STATUS, RESULTS) for p in Path(directory).rglob(name)}


SWEEP_FUNCTIONS = ("choice", "range", "tag", "int", "float")  # Hydra's override functions counted without expanding
COUNTED_TEXT = 1 << 16  # characters of overrides counted: longer ones would take Hydra's parser long


def sweep_length(override: str) -> int | None:
    """How many values the command-line override ``override`` (``seed=range(0,3)``, ``encoding=none,posenc``)
    sweeps, 1 where it sweeps none, counted without expanding it (a ``range`` of a billion values is counted,
    not listed); None where that cannot be told: a function other than ``SWEEP_FUNCTIONS`` (``glob`` needs
    the config's options; ``sort`` and ``shuffle`` expand what they sort), or an override Hydra does not parse.
    """
    called = {match.group(1) for match in re.finditer(r"([A-Za-z_]\w*)\s*\(", override.partition("=")[2])}
    if called - set(SWEEP_FUNCTIONS):
        return None
    try:
        (parsed,) = OverridesParser.create().parse_overrides([override])
        value = parsed.value() if parsed.is_sweep_override() else None
        if value is None:
            return 1
        if isinstance(value, ChoiceSweep):
            return len(value.list)
        if not isinstance(value, RangeSweep):  # glob's or interval's: not a list of values
            return None
        if all(isinstance(v, int) for v in (value.start, value.stop, value.step)):
            return len(range(value.start, value.stop, value.step))
        span = (value.stop - value.start) / value.step
        return max(0, math.ceil(span)) if math.isfinite(span) else None
    except (HydraException, ValueError, TypeError, ZeroDivisionError, OverflowError, RecursionError):
        return None


def planned_jobs(directory: Path) -> int | None:
    """How many jobs the multirun in ``directory`` launches (its ``multirun.yaml``): the product of the
    lengths of a basic sweep's overrides (``sweep_length``; each key once, the command line's over the sweeper's
    params), the trials of a search; None where there is no
    such file or that cannot be told. The file is read as data (it may come from elsewhere: bounded, nothing
    in it resolved, an interpolation counted as the text it is); one that cannot be read is an
    ``UnreadableFile`` naming it and why."""
    path = directory / "multirun.yaml"
    if not os.path.lexists(path):
        return None
    config = reading.read_yaml(path)
    hydra = config.get("hydra") if isinstance(config, dict) else None
    sweeper = hydra.get("sweeper") if isinstance(hydra, dict) else None
    if not isinstance(sweeper, dict):
        raise reading.UnreadableFile(path, "not a sweep's multirun.yaml (it has no hydra.sweeper)")
    if not str(sweeper.get("_target_")).endswith("BasicSweeper"):
        trials = sweeper.get("n_trials")
        return trials if isinstance(trials, int) and not isinstance(trials, bool) and trials >= 0 else None
    params, task = sweeper.get("params") or {}, (hydra.get("overrides") or {})
    task = task.get("task") or [] if isinstance(task, dict) else None
    if not isinstance(params, dict) or not isinstance(task, list):
        raise reading.UnreadableFile(path, "not a sweep's multirun.yaml (its sweeper's params or task overrides "
                                           "are not a mapping and a list)")
    # a key the command line sweeps replaces the sweeper's params of that key (Hydra's basic sweeper: the
    # command line takes precedence), so each key counts once, as its last override says
    overrides = list({str(override).split("=", 1)[0]: str(override)
                      for override in [f"{key}={value}" for key, value in params.items()] + task}.values())
    if sum(map(len, overrides)) > COUNTED_TEXT:
        return None
    jobs = 1
    for override in overrides:
        length = sweep_length(override)
        if length is None:
            return None
        jobs *= length
    return jobs


CPU_UNITS = ("avx2", "avx512f", "avx512_bf16", "amx_bf16")  # /proc/cpuinfo flags that change a CPU's timings


def cpu_model(cpuinfo: str) -> str:
    """The first CPU's model name and which of ``CPU_UNITS`` it has, from a Linux ``/proc/cpuinfo`` text:
    e.g. "Intel(R) Xeon(R) Processor [avx2 avx512f avx512_bf16 amx_bf16]"; "CPU" where the text names none.

    >>> cpu_model("model name : AMD EPYC 9R14\\nflags : fpu avx2 avx512f\\n")
    'AMD EPYC 9R14 [avx2 avx512f]'
    """
    fields = {}
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    flags = set(fields.get("flags", "").split())
    units = " ".join(unit for unit in CPU_UNITS if unit in flags)
    return f"{fields.get('model name', 'CPU')} [{units}]" if units else fields.get("model name", "CPU")


def machine() -> dict:
    """Where a run's times were measured: host name and compute device (a CPU's model and units, whose
    timings differ from machine to machine)."""
    if torch.cuda.is_available():
        device = f"{torch.cuda.get_device_name()} (CUDA {torch.version.cuda})"
    else:
        try:
            model = cpu_model(Path("/proc/cpuinfo").read_text())
        except OSError:
            model = "CPU"
        device = f"{model} ({os.cpu_count()} cores, {torch.get_num_threads()} torch threads)"
    return {"host": socket.gethostname(), "device": device}


def checkpoint_record(run_dir: Path, checkpoint: Path) -> dict:
    """What ``results.json`` says of the checkpoint its test scored: ``path`` (relative to the run
    directory where it lies inside it) and ``sha256``."""
    checkpoint = Path(checkpoint)
    try:
        path = checkpoint.resolve().relative_to(Path(run_dir).resolve())
    except ValueError:  # elsewhere
        path = checkpoint.resolve()
    return {"path": str(path), "sha256": sha256(checkpoint)}
