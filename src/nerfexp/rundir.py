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

A directory belongs to one run, and a run writes over nothing a user made: ``RunDirectoryGuard`` starts
a run only in a new or empty directory, the run that ``resume`` continues, or that of a run that ended
unfinished without saving a checkpoint (replaced), and a sweep only in a new or empty directory; it
refuses before Hydra writes into the directory. ``RUN_MADE`` lists what nerfexp's commands make there.

A finished (or interrupted) run is read back by ``find_run``, ``run_config`` and ``load_module``
(together: ``load_run``).
"""

import contextlib
import hashlib
import json
import os
import pickle
import socket
import sys
import tempfile
import time
import warnings
import zipfile
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
from nerfexp.files import TEMPORARY, atomic_write, folder_entries, foreign_message, is_made
from nerfexp.memory import network_bytes, require_memory
from nerfexp.saved_configs import as_data

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
# what nerfexp-report writes into its folder (a sweep's or a run's, by default), and what Hydra's multirun, the
# Optuna sweeper and the submitit launchers write into a sweep's
REPORT_MADE = ("report.md", "report.csv", "report.html", "psnr_vs_time.png", "pareto.png", "report_images/view*/*.png")
SWEEP_MADE = ("multirun.yaml", "optimization_results.yaml", ".submitit")
# every entry nerfexp's commands make in a run directory (``nerfexp.files.is_made`` patterns; the run's log,
# ``hydra.job.name``.log, aside): the run's files, Hydra's, the checkpoints, the training guards', each
# logger's (conf/logger/, and the images of a logger without a folder of its own), nerfexp-eval's,
# nerfexp-render's, nerfexp-export's, nerfexp-view's and nerfexp-report's, and interrupted atomic writes
RUN_MADE = (STATUS, RESULTS, METRICS, f"{TEST_DIR}/r_*.png", RUN_CONFIG.parent.name, LAST_CHECKPOINT.parent.name,
            "debug", "tensorboard", "csv", "wandb", "mlflow.db*", "mlartifacts", "images", EVAL, RENDER_DIR,
            EXPORT_DIR, CAMERA_PATH.as_posix(), *REPORT_MADE, *TEMPORARY)

# Where the classes of a run's config lived before the package was split into layers (and the data group
# held the field's density noise): a run made by an earlier nerfexp is read as if made by this one.
MOVED_TARGETS = {  # the first match of a target wins; callbacks are not read back (saved_configs.TRAINING_ONLY)
    "nerfexp.module.": "nerfexp.training.module.",
    "nerfexp.guards.": "nerfexp.training.guards.",
    "nerfexp.renderer.": "nerfexp.nerf.volume_renderer.",
    "nerfexp.fields.": "nerfexp.nerf.fields.",
    "nerfexp.encodings.": "nerfexp.nerf.encodings.",
    "nerfexp.occupancy.": "nerfexp.nerf.occupancy.",
}
OLD_NOISE = "density_noise_std: ${oc.select:data.density_noise_std,0.0}"  # the field's line while data held it


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


CLAIM_DRAFTS = (f".{STATUS}.*.tmp",)  # a status being claimed (``claim``): a run starting at this moment


def saved_checkpoints(run_dir: Path) -> list[Path]:
    """The checkpoints a run saved (``checkpoints/*.ckpt``): ``last.ckpt`` first, then the newest first."""
    found = [path for path in (run_dir / LAST_CHECKPOINT.parent).glob("*.ckpt") if path.is_file()]
    return sorted(found, key=lambda path: (path.name != LAST_CHECKPOINT.name, -path.stat().st_mtime))


def ended_unfinished(status: dict | None) -> bool:
    """Whether the run whose ``status.json`` reads ``status`` ended without finishing: ``failed``, or
    ``running`` in a process of this host that no longer runs (``process_alive``; killed, out of memory).
    A run of another host, or with no status, may still run: not."""
    if status is None or status.get("state") == "failed":
        return status is not None
    pid = status.get("pid")
    return (status.get("state") == "running" and status.get("host") == socket.gethostname()
            and isinstance(pid, int) and not process_alive(pid, status.get("process_start")))


def admit_run(run_dir: Path, resume: str | None, log: str) -> list[str] | None:
    """The entries (``nerfexp.files.folder_entries``) to remove from ``run_dir`` before a run claims it:
    none where it holds no files; all of them where it holds a run that ended unfinished
    (``ended_unfinished``) and saved no checkpoint. None where it holds the run that ``resume`` (a
    checkpoint inside it) continues: the directory is that run's already.
    Otherwise a NerfexpError saying what it holds and what to do: files that no nerfexp command made
    (``RUN_MADE``, and the run's ``log``; any file, where it holds no run: ``held_run``), or another run
    (continued with ``resume=`` one of its checkpoints, where it saved one: ``saved_checkpoints``)."""
    held = held_run(run_dir)
    entries = folder_entries(run_dir)
    made = CLAIM_DRAFTS if held is None else (*RUN_MADE, log)
    if foreign := [entry for entry in entries if not is_made(entry, made)]:
        raise NerfexpError(foreign_message(run_dir, foreign, "nerfexp",
                                           "choose a new or empty directory (hydra.run.dir=...)"))
    if held is None:
        return []
    if resume is not None and run_dir.resolve() in Path(resume).resolve().parents:
        return None
    if checkpoints := saved_checkpoints(run_dir):
        raise NerfexpError(f"{run_dir} holds {held}: continue it with resume={checkpoints[0]} "
                           f"hydra.run.dir={run_dir}, or choose another directory (hydra.run.dir=...)")
    if not ended_unfinished(read_json(run_dir / STATUS)):
        raise NerfexpError(f"{run_dir} holds {held}: choose another directory (hydra.run.dir=...)")
    return entries


def remove_entries(folder: Path, entries: list[str]) -> None:
    """Delete ``entries`` (``/``-separated paths relative to ``folder``), then the folders they leave
    empty inside ``folder``: nothing else."""
    emptied = set()
    for entry in entries:
        (folder / entry).unlink(missing_ok=True)
        emptied.update(Path(entry).parents)
    for parent in sorted(emptied - {Path(".")}, key=lambda path: len(path.parts), reverse=True):
        with contextlib.suppress(OSError):  # a folder that still holds something stays
            (folder / parent).rmdir()


class RunDirectoryGuard(Callback):
    """Hydra callback: a run starts only in a directory of its own, checked before Hydra writes its
    config there (``hydra.callbacks.run_directory``): nothing a user made is written over.

    A single run stops with one line (exit status 1) unless ``hydra.run.dir`` is new or empty, holds the
    run that ``resume`` continues, or holds a run that ended unfinished and saved no checkpoint, whose
    files are then removed, saying so in one line (``admit_run``); then it claims the directory
    (``claim``). A multirun stops unless ``hydra.sweep.dir`` is new or empty.
    In a distributed job started by SLURM every process runs this; global rank 0 checks and claims.
    It stops with ``SystemExit``: Hydra turns a callback's exceptions into warnings and goes on."""

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        if not is_global_zero():
            return
        run_dir = Path(config.hydra.run.dir)
        try:
            replaced = admit_run(run_dir, config.get("resume"), f"{config.hydra.job.name}.log")
            if replaced is None:  # the run continued
                return
            if replaced:
                print(f"nerfexp: {run_dir} holds a run that ended unfinished and saved no checkpoint: replacing it, "
                      f"removing its {len(replaced)} files ({', '.join(replaced[:3])}{', ...' * (len(replaced) > 3)})",
                      file=sys.stderr)
                remove_entries(run_dir, replaced)
            if not claim(run_dir, list(config.hydra.overrides.task)):
                raise NerfexpError(f"{run_dir} holds a run that started at the same time: choose another "
                                   "directory (hydra.run.dir=...)")
        except NerfexpError as error:
            raise SystemExit(f"nerfexp: error: {error}") from None
        except OSError as error:
            raise SystemExit(f"nerfexp: error: cannot write the run directory {run_dir}: {error.strerror} "
                             "(choose another with hydra.run.dir=...)") from None

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
        if entries := folder_entries(sweep_dir):
            raise SystemExit("nerfexp: error: " + foreign_message(
                sweep_dir, entries, "this sweep", "choose a new or empty directory (hydra.sweep.dir=...)"))


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


def _current(text: str, source: Path) -> DictConfig:
    """A run config's text (read from ``source``) as this version's config, read as data
    (``nerfexp.saved_configs.as_data``, before anything in it is resolved): ``MOVED_TARGETS`` paths made
    current, and ``data.density_noise_std`` moved to ``model.renderer.field`` (``OLD_NOISE``: the field
    once read it with a resolver, whose default was 0.0)."""
    for old, new in MOVED_TARGETS.items():
        text = text.replace(f"_target_: {old}", f"_target_: {new}")  # a replaced target matches no later old
    cfg = OmegaConf.create(text.replace(OLD_NOISE, "density_noise_std: 0.0"))
    if not isinstance(cfg, DictConfig):
        raise ConfigError(f"{source}: not a config nerfexp can read (a mapping of keys was expected)")
    cfg = as_data(cfg, source)
    if "density_noise_std" in cfg.get("data", {}):
        with open_dict(cfg):
            cfg.model.renderer.field.density_noise_std = cfg.data.pop("density_noise_std")
    return cfg


def run_config(run_dir: Path, overrides: list[str] = ()) -> DictConfig:
    """The config a run used (its ``RUN_CONFIG``), with ``KEY=VALUE`` ``overrides`` of existing keys
    (e.g. ``data.root=...`` for a scene that moved). The file is read as data: a ``_target_`` in it that
    is not one of the classes nerfexp builds, or an interpolation that is not a plain reference to another
    of its keys, is a ConfigError (``nerfexp.saved_configs``), and the keys only training builds are left
    out. A reference that the config cannot follow is a ConfigError naming the key, before anything is built."""
    source = Path(run_dir) / RUN_CONFIG
    try:
        cfg = _current(source.read_text(), source)
    except (OmegaConfBaseException, yaml.YAMLError, UnicodeDecodeError) as error:
        raise ConfigError(f"{source}: not a config nerfexp can read ({str(error).splitlines()[0]})") from None
    OmegaConf.set_struct(cfg, True)  # an override of a key the run does not have is a typo, not a new key
    try:
        cfg = OmegaConf.merge(cfg, OmegaConf.from_dotlist(list(overrides)))
    except OmegaConfBaseException as error:
        raise ConfigError(f"cannot apply {' '.join(overrides)} to {Path(run_dir) / RUN_CONFIG}: "
                          f"{str(error).splitlines()[0]}") from None
    try:
        OmegaConf.to_container(cfg, resolve=True)  # plain references only (and the overrides'): nothing runs
    except OmegaConfBaseException as error:
        where = f" at {error.full_key}" if error.full_key else ""
        raise ConfigError(f"{source}: cannot resolve the config{where}: {str(error).splitlines()[0]}") from None
    return cfg


def not_a_checkpoint(path: Path, error: Exception) -> str:
    """What file ``path``, which ``torch.load`` could not read as data (``error``), is, in a few words: never
    torch's own message, whose advice to load it with ``weights_only=False`` would run any code it holds."""
    if path.stat().st_size == 0:
        return "an empty file"
    if not zipfile.is_zipfile(path):
        return "not a whole zip archive as torch.save writes: cut short, or another kind of file"
    if isinstance(error, pickle.UnpicklingError):
        return "it holds objects other than tensors, numbers, strings and containers of them"
    return "a damaged zip archive"


def read_checkpoint(path: Path) -> dict:
    """A Lightning checkpoint's contents read as data (``weights_only``: tensors and plain containers;
    a pickle that would run code is refused), on the CPU; a NerfexpError naming the file otherwise."""
    path = Path(path)
    if not path.is_file():
        raise NerfexpError(f"{path}: no such checkpoint file")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # torch's notes on pickle protocols: the error below says what matters
            state = torch.load(path, map_location="cpu", weights_only=True)
    except OSError as error:
        raise NerfexpError(f"{path}: cannot read the checkpoint ({error.strerror})") from None
    except Exception as error:  # torch raises any type (IndexError, KeyError, ...) on bytes it cannot parse
        raise NerfexpError(f"{path}: not a checkpoint ({not_a_checkpoint(path, error)}); nerfexp reads checkpoints "
                           "as data only, never running code in them") from None
    if not isinstance(state, dict) or not isinstance(state.get("state_dict"), dict) or "global_step" not in state:
        raise NerfexpError(f"{path}: not a Lightning checkpoint (expected a state_dict and a global_step)")
    return state


def load_module(cfg: DictConfig, checkpoint: Path) -> tuple[L.LightningModule, int]:
    """The run's model (``cfg.model``) with the weights of ``checkpoint`` (``read_checkpoint``), on the
    CPU, and the number of optimizer steps it had taken."""
    fill_ray_bounds(cfg)  # a run's saved config holds null where the scene chose near and far
    module = instantiate(cfg.model)
    state = read_checkpoint(checkpoint)
    check_weights(state["state_dict"], module, checkpoint)
    module.load_state_dict(state["state_dict"])
    return module, state["global_step"]


def check_weights(weights: dict[str, torch.Tensor], module: torch.nn.Module, checkpoint: Path) -> None:
    """A NerfexpError in one line where a checkpoint's ``weights`` (a state_dict) do not fit ``module``: the
    first parameter or buffer that one has and the other lacks, or whose shapes differ, with both shapes
    (where torch's ``load_state_dict`` would list every one, a line each)."""
    expected = module.state_dict()
    for name in [*expected, *(name for name in weights if name not in expected)]:
        if name not in weights or name not in expected:
            where = "the checkpoint" if name not in weights else "this run's model"
            raise NerfexpError(f"{checkpoint}: not a checkpoint of this run's model: {name} is missing from {where}")
        if weights[name].shape != expected[name].shape:
            raise NerfexpError(f"{checkpoint}: not a checkpoint of this run's model: {name} has shape "
                               f"{list(weights[name].shape)} there and {list(expected[name].shape)} in this run's "
                               "model (another network size?)")


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
    if chunk is not None:  # refused where it cannot fit, before any rendering
        samples, field = module.renderer.samples_per_ray, cfg.model.renderer.field
        require_memory(f"--chunk {chunk}", f"an evaluation of {chunk} rays x {samples} samples",
                       network_bytes(chunk, samples, field.width, field.depth, training=False))
        module.chunk = chunk
    module.to("cuda" if torch.cuda.is_available() else "cpu").eval()
    return TrainedRun(run_dir, checkpoint, cfg, module, step)
