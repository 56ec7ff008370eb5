"""The run directory: the one place that knows the names of the files a run leaves, and how a run is
found and read back.

A run's directory holds (every file written atomically):

- ``status.json``: ``running`` (with host, process id and the process's start), ``finished`` or
  ``failed`` (with the error), and the run's command-line overrides, so a report can list jobs that
  crashed or still run.
- ``metrics.jsonl``: one JSON object per evaluation: step, wall_time_s, split, psnr, ssim (means).
- ``results.json``: final test means and per-view scores, last validation PSNR, training time,
  throughput, parameters, the machine, the resolved choices and overrides
  (``nerfexp.training.recorders.RunRecorder``).
- ``test/``: each test view's render (``r_{i}.png``), ground truth (``r_{i}_target.png``), absolute
  error (``r_{i}_error.png``) and depth (``r_{i}_depth.png``).
- ``checkpoints/last.ckpt``, ``.hydra/config.yaml`` (the composed config, as Hydra saves it).
- ``eval.json`` (``nerfexp-eval``), ``render/`` (``nerfexp-render``), ``export/`` (``nerfexp-export``),
  ``view/camera_path.json`` (``nerfexp-view``'s saved camera path), ``debug/`` (the training guards).

A directory belongs to one run: ``RunDirectoryGuard`` refuses to start a run in a directory that
holds another one (or a sweep in one that holds an earlier sweep's runs), before Hydra writes into it.

A finished (or interrupted) run is read back by ``find_run``, ``run_config`` and ``load_module``
(together: ``load_run``).
"""

import contextlib
import hashlib
import json
import os
import pickle
import socket
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import lightning as L
import torch
import yaml
from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.experimental.callback import Callback
from hydra.utils import instantiate
from lightning.pytorch.utilities.rank_zero import rank_zero_only
from omegaconf import DictConfig, OmegaConf, open_dict
from omegaconf.errors import OmegaConfBaseException

from nerfexp.data.datamodule import fill_ray_bounds
from nerfexp.errors import ConfigError, NerfexpError
from nerfexp.files import atomic_write
from nerfexp.saved_configs import check_saved_config

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

# Where the classes of a run's config lived before the package was split into layers (and the data group
# held the field's density noise): a run made by an earlier nerfexp is read as if made by this one.
MOVED_TARGETS = {  # the first match of a target wins
    "nerfexp.module.FlushDenormals": "nerfexp.training.callbacks.FlushDenormals",
    "nerfexp.module.": "nerfexp.training.module.",
    "nerfexp.guards.": "nerfexp.training.guards.",
    "nerfexp.renderer.": "nerfexp.nerf.volume_renderer.",
    "nerfexp.fields.": "nerfexp.nerf.fields.",
    "nerfexp.encodings.": "nerfexp.nerf.encodings.",
    "nerfexp.occupancy.": "nerfexp.nerf.occupancy.",
}


def is_global_zero() -> bool:
    """Whether this process is global rank 0, the one that writes a run's files: always in a run of one
    process; known before any trainer exists from the environment a launcher sets (``RANK``,
    ``LOCAL_RANK``, ``SLURM_PROCID``), and kept up to date by Lightning's strategies."""
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


def read_metrics(run_dir: Path) -> list[dict]:
    """The records of a run's ``metrics.jsonl``, in order; none where it has none. A last line still
    being written (no newline yet) is left out; a line that is not JSON is a ValueError naming it."""
    path = Path(run_dir) / METRICS
    records = []
    for number, line in enumerate(path.read_text().split("\n")[:-1] if path.exists() else [], 1):
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
    basic sweep, the trials of a search; None where that cannot be told."""
    path = directory / "multirun.yaml"
    if not path.exists():
        return None
    hydra = OmegaConf.load(path).hydra
    sweeper = hydra.sweeper
    if sweeper._target_.endswith("BasicSweeper"):
        params = [f"{key}={value}" for key, value in (sweeper.params or {}).items()] + list(hydra.overrides.task)
        batches = BasicSweeper.split_arguments(OverridesParser.create().parse_overrides(params), None)
        return sum(len(batch) for batch in batches)
    return sweeper.get("n_trials")


def held_run(run_dir: Path) -> str | None:
    """What run ``run_dir`` holds, described (its state and overrides, from ``status.json``), or None
    where it holds none (no status, results, metrics or checkpoints)."""
    status = read_json(run_dir / STATUS)
    if status is not None:
        return f"a {status.get('state')} run ({' '.join(status.get('overrides', [])) or 'no overrides'})"
    if any((run_dir / name).exists() for name in (RESULTS, METRICS, LAST_CHECKPOINT.parent)):
        return "a run's results"
    return None


def claim(run_dir: Path, overrides: list[str]) -> bool:
    """Make ``run_dir`` this run's: its ``status.json`` (``running``) is created only where none exists,
    whole (written beside it, then hard-linked into place, which fails where the name is taken), so of
    two runs started into one directory at once one gets it, and no reader sees half a status. Returns
    whether this run did."""
    run_dir.mkdir(parents=True, exist_ok=True)
    status = status_bytes("running", overrides)
    fd, draft = tempfile.mkstemp(dir=run_dir, prefix=f".{STATUS}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as file:
            file.write(status)
        os.chmod(draft, 0o644)
        os.link(draft, run_dir / STATUS)
    except FileExistsError:
        return False
    except OSError:  # a file system without hard links: create the name exclusively, then write it
        try:
            fd = os.open(run_dir / STATUS, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            return False
        with os.fdopen(fd, "wb") as file:
            file.write(status)
    finally:
        os.unlink(draft)
    return True


class RunDirectoryGuard(Callback):
    """Hydra callback: a run starts only in a directory of its own, checked before Hydra writes its
    config there (``hydra.callbacks.run_directory``).

    A single run stops with one line (exit status 1) where ``hydra.run.dir`` holds another run
    (``held_run``), unless ``resume`` names a checkpoint inside it (the run continued); otherwise it
    claims the directory (``claim``). A multirun stops where ``hydra.sweep.dir`` holds runs already.
    In a distributed job started by SLURM every process runs this; global rank 0 checks and claims.
    It stops with ``SystemExit``: Hydra turns a callback's exceptions into warnings and goes on."""

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        if not is_global_zero():
            return
        run_dir = Path(config.hydra.run.dir)
        resume = config.get("resume")
        if resume is not None and run_dir.resolve() in Path(resume).resolve().parents:
            return
        held = held_run(run_dir)
        try:
            if held is None and not claim(run_dir, list(config.hydra.overrides.task)):
                held = "a run that started at the same time"
        except OSError as error:
            raise SystemExit(f"nerfexp: error: cannot write the run directory {run_dir}: {error.strerror} "
                             "(choose another with hydra.run.dir=...)") from None
        if held is not None:
            raise SystemExit(f"nerfexp: error: {run_dir} holds {held}: continue it with "
                             f"resume={run_dir / LAST_CHECKPOINT} hydra.run.dir={run_dir}, or choose another "
                             f"directory (hydra.run.dir=...)")

    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        try:
            sweep_dir.mkdir(parents=True, exist_ok=True)
            tempfile.TemporaryFile(dir=sweep_dir).close()  # writable, before any job starts
        except OSError as error:
            raise SystemExit(f"nerfexp: error: cannot write the sweep directory {sweep_dir}: {error.strerror} "
                             "(choose another with hydra.sweep.dir=...)") from None
        runs = find_run_dirs(sweep_dir)
        if runs:
            raise SystemExit(f"nerfexp: error: {sweep_dir} holds the runs of an earlier sweep ({len(runs)}): choose "
                             f"another directory (hydra.sweep.dir=...)")


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


def find_run(path: str | Path) -> tuple[Path, Path]:
    """``(run directory, checkpoint)`` of ``path``: a run directory (the checkpoint its final test scored,
    as ``results.json`` records it, checked against its SHA-256; else ``checkpoints/last.ckpt``) or a
    checkpoint file in one (``RUN_DIR/checkpoints/NAME.ckpt``: the run directory two levels up)."""
    path = Path(path)
    if not path.exists():
        raise NerfexpError(f"{path} does not exist: expected a run directory or a checkpoint file in one")
    run_dir, checkpoint = (path, path / LAST_CHECKPOINT) if path.is_dir() else (path.parent.parent, path)
    if not (run_dir / RUN_CONFIG).is_file():
        raise NerfexpError(f"{run_dir} is not a run directory: it has no {RUN_CONFIG}")
    tested = (read_json(run_dir / RESULTS) or {}).get("checkpoint") if path.is_dir() else None
    if tested is not None:
        checkpoint = run_dir / tested["path"]
        if checkpoint.is_file() and sha256(checkpoint) != tested["sha256"]:
            raise NerfexpError(f"{checkpoint} is not the checkpoint the run's test scored (its SHA-256 differs "
                               f"from {run_dir / RESULTS}'s): name a checkpoint file to use it anyway")
    if not checkpoint.is_file():
        raise NerfexpError(f"{checkpoint} does not exist: the run in {run_dir} has saved no checkpoint")
    return run_dir, checkpoint


def _current(text: str) -> DictConfig:
    """A run config's text read as this version's config: ``MOVED_TARGETS`` paths made current, and
    ``data.density_noise_std`` moved to ``model.renderer.field``."""
    for old, new in MOVED_TARGETS.items():
        text = text.replace(f"_target_: {old}", f"_target_: {new}")  # a replaced target matches no later old
    cfg = OmegaConf.create(text)
    if "density_noise_std" in cfg.get("data", {}):
        with open_dict(cfg):
            cfg.model.renderer.field.density_noise_std = cfg.data.pop("density_noise_std")
    return cfg


def run_config(run_dir: Path, overrides: list[str] = ()) -> DictConfig:
    """The config a run used (its ``RUN_CONFIG``), with ``KEY=VALUE`` ``overrides`` of existing keys
    (e.g. ``data.root=...`` for a scene that moved). The file is read as data: a ``_target_`` in it that
    is not one of the classes nerfexp builds is a ConfigError (``nerfexp.saved_configs``)."""
    source = Path(run_dir) / RUN_CONFIG
    try:
        cfg = _current(source.read_text())
    except (OmegaConfBaseException, yaml.YAMLError, UnicodeDecodeError) as error:
        raise ConfigError(f"{source}: not a config nerfexp can read ({str(error).splitlines()[0]})") from None
    if not isinstance(cfg, DictConfig):
        raise ConfigError(f"{source}: not a config nerfexp can read (a mapping of keys was expected)")
    check_saved_config(cfg, source)
    OmegaConf.set_struct(cfg, True)  # an override of a key the run does not have is a typo, not a new key
    try:
        return OmegaConf.merge(cfg, OmegaConf.from_dotlist(list(overrides)))
    except OmegaConfBaseException as error:
        raise ConfigError(f"cannot apply {' '.join(overrides)} to {Path(run_dir) / RUN_CONFIG}: "
                          f"{str(error).splitlines()[0]}") from None


def read_checkpoint(path: Path) -> dict:
    """A Lightning checkpoint's contents read as data (``weights_only``: tensors and plain containers;
    a pickle that would run code is refused), on the CPU; a NerfexpError naming the file otherwise."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, EOFError, pickle.UnpicklingError) as error:
        raise NerfexpError(f"{path}: not a checkpoint nerfexp can read as data "
                           f"({type(error).__name__}: {str(error).splitlines()[0]})") from None
    if not isinstance(state, dict) or not isinstance(state.get("state_dict"), dict) or "global_step" not in state:
        raise NerfexpError(f"{path}: not a Lightning checkpoint (expected a state_dict and a global_step)")
    return state


def load_module(cfg: DictConfig, checkpoint: Path) -> tuple[L.LightningModule, int]:
    """The run's model (``cfg.model``) with the weights of ``checkpoint`` (``read_checkpoint``), on the
    CPU, and the number of optimizer steps it had taken."""
    fill_ray_bounds(cfg)  # a run's saved config holds null where the scene chose near and far
    module = instantiate(cfg.model)
    state = read_checkpoint(checkpoint)
    try:
        module.load_state_dict(state["state_dict"])
    except RuntimeError as error:
        raise NerfexpError(f"{checkpoint}: not a checkpoint of this run's model "
                           f"({type(error).__name__}: {str(error).splitlines()[0]})") from None
    return module, state["global_step"]


class TrainedRun(NamedTuple):
    """A run read back for rendering (``load_run``)."""

    run_dir: Path
    checkpoint: Path
    cfg: DictConfig  # the run's saved config, with the caller's overrides
    module: L.LightningModule  # with the checkpoint's weights, in eval mode
    step: int  # optimizer steps the checkpoint had taken


def load_run(run: str | Path, overrides: list[str] = (), chunk: int | None = None,
             refuse: Callable[[Path, DictConfig], None] | None = None) -> TrainedRun:
    """The run at ``run`` (a run directory, or a checkpoint file in one) read as data (``find_run``,
    ``run_config`` with ``overrides``, ``load_module``): its module in eval mode on the GPU where there is
    one, rendering ``chunk`` rays at once (None: the run's ``model.chunk``). ``refuse(run_dir, saved
    config)``, where given, is called before the checkpoint is read, to raise for runs a command cannot use."""
    run_dir, checkpoint = find_run(run)
    if refuse is not None:
        refuse(run_dir, run_config(run_dir))
    cfg = run_config(run_dir, overrides)
    module, step = load_module(cfg, checkpoint)
    if chunk is not None:
        module.chunk = chunk
    module.to("cuda" if torch.cuda.is_available() else "cpu").eval()
    return TrainedRun(run_dir, checkpoint, cfg, module, step)
