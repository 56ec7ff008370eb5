"""The run directory's layout: the names of the files a run leaves, its status and records, written
atomically and read back, and how runs are found under a folder (the package's docstring lists them)."""

import contextlib
import hashlib
import json
import os
import socket
import time
from pathlib import Path

import torch
from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import OmegaConf

from nerfexp.files import TEMPORARY, atomic_write

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
# what nerfexp-report writes into its folder (a sweep's or a run's, by default): its pages, its plots, and the
# folder of the page's pictures (the only place these names are spelled)
REPORT_MD, REPORT_CSV, REPORT_HTML = "report.md", "report.csv", "report.html"
PSNR_PLOT, PARETO_PLOT = "psnr_vs_time.png", "pareto.png"
REPORT_IMAGES = "report_images"
REPORT_MADE = (REPORT_MD, REPORT_CSV, REPORT_HTML, PSNR_PLOT, PARETO_PLOT, f"{REPORT_IMAGES}/view*/*.png")
# what Hydra's multirun, the Optuna sweeper and the submitit launchers write into a sweep's folder
SWEEP_MADE = ("multirun.yaml", "optimization_results.yaml", ".submitit")
# every entry nerfexp's commands make in a run directory (``nerfexp.files.is_made`` patterns; the run's log,
# ``hydra.job.name``.log, aside): the run's files, Hydra's, the checkpoints, the training guards', each
# logger's (conf/logger/, and the images of a logger without a folder of its own), nerfexp-eval's,
# nerfexp-render's, nerfexp-export's, nerfexp-view's and nerfexp-report's, and interrupted atomic writes
RUN_MADE = (STATUS, RESULTS, METRICS, f"{TEST_DIR}/r_*.png", RUN_CONFIG.parent.name, LAST_CHECKPOINT.parent.name,
            "debug", "tensorboard", "csv", "wandb", "mlflow.db*", "mlartifacts", "images", EVAL, RENDER_DIR,
            EXPORT_DIR, CAMERA_PATH.as_posix(), *REPORT_MADE, *TEMPORARY)

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
    """Record a run's ``state`` in its ``status.json`` (``status_bytes``), replacing the last one."""
    atomic_write(Path(output_dir) / STATUS, status_bytes(state, overrides, **details))


def write_json(path: Path, record: dict) -> None:
    """A run's JSON file (results, evaluation), indented, written atomically."""
    atomic_write(path, json.dumps(record, indent=2).encode())


def read_json(path: Path) -> dict | None:
    """The JSON file ``path``; None where it does not exist."""
    return json.loads(path.read_text()) if path.exists() else None


def append_metrics(output_dir: str | Path, record: dict) -> None:
    """Add one evaluation's ``record`` as a line of the run's ``metrics.jsonl``: one ``write`` of the
    whole line to the file opened for appending, which the kernel places at the end of the file as one
    piece, so the lines of several processes never overwrite or cut into each other."""
    path = Path(output_dir) / METRICS
    path.parent.mkdir(parents=True, exist_ok=True)
    line = (json.dumps(record) + "\n").encode()
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        written = os.write(fd, line)
    finally:
        os.close(fd)
    if written != len(line):  # a full disk: say so rather than leave a line that reads as another
        raise OSError(f"{path}: wrote {written} of the {len(line)} bytes of a metrics line")


def read_metrics(run_dir: Path, ended: bool = False) -> list[dict]:
    """The records of a run's ``metrics.jsonl``, in order; none where it has none. A last line without
    its newline is one still being written where the run may still run: left out; where the run has
    ``ended`` (finished, failed or killed) nothing will finish it, so it was cut: a ValueError naming it,
    as is a line that is not JSON."""
    path = Path(run_dir) / METRICS
    lines = path.read_text().split("\n") if path.exists() else [""]
    if ended and lines[-1]:
        raise ValueError(f"line {len(lines)}, the last, is cut (no newline, and the run has ended)")
    records = []
    for number, line in enumerate(lines[:-1], 1):
        try:
            records.append(json.loads(line))
        except ValueError as error:
            raise ValueError(f"line {number} is not JSON ({error})") from None
    return records


def find_run_dirs(directory: Path) -> set[Path]:
    """Every run directory under ``directory`` (itself included): a folder holding ``status.json`` or
    ``results.json``."""
    return {p.parent for name in (STATUS, RESULTS) for p in Path(directory).rglob(name)}


def planned_jobs(directory: Path) -> int | None:
    """How many jobs the multirun in ``directory`` launches (its ``multirun.yaml``): the grid of a
    basic sweep, the trials of a search; None where that cannot be told. The file is read as data (it may
    come from elsewhere): nothing in it is resolved, an interpolation is counted as the text it is."""
    path = directory / "multirun.yaml"
    if not path.exists():
        return None
    hydra = OmegaConf.to_container(OmegaConf.load(path), resolve=False)["hydra"]
    sweeper = hydra["sweeper"]
    if str(sweeper["_target_"]).endswith("BasicSweeper"):
        params = [f"{key}={value}" for key, value in (sweeper.get("params") or {}).items()] + hydra["overrides"]["task"]
        batches = BasicSweeper.split_arguments(OverridesParser.create().parse_overrides(params), None)
        return sum(len(batch) for batch in batches)
    trials = sweeper.get("n_trials")
    return trials if isinstance(trials, int) else None


def machine() -> dict:
    """Where a run's times were measured: host name and compute device."""
    if torch.cuda.is_available():
        device = f"{torch.cuda.get_device_name()} (CUDA {torch.version.cuda})"
    else:
        device = f"CPU ({os.cpu_count()} cores, {torch.get_num_threads()} torch threads)"
    return {"host": socket.gethostname(), "device": device}


def sha256(path: Path) -> str:
    """The SHA-256 of a file's bytes, hexadecimal."""
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def checkpoint_record(run_dir: Path, checkpoint: Path) -> dict:
    """What ``results.json`` says of the checkpoint its test scored: ``path`` (relative to the run
    directory where it lies inside it) and ``sha256``."""
    checkpoint = Path(checkpoint)
    try:
        path = checkpoint.resolve().relative_to(Path(run_dir).resolve())
    except ValueError:  # elsewhere
        path = checkpoint.resolve()
    return {"path": str(path), "sha256": sha256(checkpoint)}
