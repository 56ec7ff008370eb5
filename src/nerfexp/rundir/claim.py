"""A directory belongs to one run: ``RunDirectoryGuard`` (a Hydra callback) starts a run only in a new or
empty directory, the run that ``resume`` continues, or that of a run that ended unfinished without a
checkpoint, and a sweep only in a new or empty directory, before Hydra writes into it; ``claim``
makes the run's status the directory's atomically. What a run replaces or removes there is known to be
nerfexp's by the directory's manifest (``nerfexp.manifest``), never by its name."""

import contextlib
import os
import sys
import tempfile
from pathlib import Path

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from nerfexp import manifest
from nerfexp.errors import NerfexpError, callback_refusals
from nerfexp.files import folder_entries, foreign_message, is_made
from nerfexp.rundir.layout import (
    LAST_CHECKPOINT,
    METRICS,
    RESULTS,
    RUN_REWRITES,
    STATUS,
    find_run_dirs,
    is_global_zero,
    read_json,
    status_bytes,
)
from nerfexp.rundir.records import STATUS_FIELDS, record_problem
from nerfexp.rundir.state import ENDED_UNFINISHED, read_state, status_state


def held_run(run_dir: Path) -> str | None:
    """What run ``run_dir`` holds, described (its state and overrides, from ``status.json``), or None
    where it holds none (no status, results, metrics or checkpoints)."""
    status = read_json(run_dir / STATUS)
    if status is not None and (problem := record_problem(status, STATUS_FIELDS, ("state",))) is not None:
        return f"a run whose {STATUS} is not as nerfexp writes it ({problem})"
    if status is not None:  # its state as it is: a run whose process is gone was killed (nerfexp.rundir.state)
        return f"a {status_state(status).state} run ({' '.join(status.get('overrides', [])) or 'no overrides'})"
    if any((run_dir / name).exists() for name in (RESULTS, METRICS, LAST_CHECKPOINT.parent)):
        return "a run's results"
    return None


def claim(run_dir: Path, overrides: list[str]) -> bool:
    """Make ``run_dir`` this run's: its ``status.json`` (``running``) is created only where none exists,
    whole (written beside it, then hard-linked into place, which fails where the name is taken), so of
    two runs started into one directory at once one gets it, and no reader sees half a status; the one
    that did records it in the directory's manifest. Returns whether this run did."""
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
    manifest.record(run_dir, [STATUS])
    return True


CLAIM_DRAFTS = (f".{STATUS}.*.tmp",)  # a status being claimed (``claim``): a run starting at this moment


def saved_checkpoints(run_dir: Path) -> list[Path]:
    """The checkpoints a run saved (``checkpoints/*.ckpt``): ``last.ckpt`` first, then the newest first."""
    found = [path for path in (run_dir / LAST_CHECKPOINT.parent).glob("*.ckpt") if path.is_file()]
    return sorted(found, key=lambda path: (path.name != LAST_CHECKPOINT.name, -path.stat().st_mtime))


def ended_unfinished(run_dir: Path) -> bool:
    """Whether the run in ``run_dir`` ended without finishing (``nerfexp.rundir.state``): ``failed``, or ``killed``
    (its status says ``running`` in a process of this host that no longer runs; out of memory, SIGKILL). A run of
    another host, or with no status or one not as nerfexp writes it, may still run: not."""
    state = read_state(run_dir)
    return state is not None and state.state in ENDED_UNFINISHED


def admit_run(run_dir: Path, resume: str | None) -> list[str] | None:
    """The entries (``nerfexp.files.folder_entries``, the manifest's own aside) to remove from ``run_dir``
    before a run claims it: none where it holds no files; all of them where it holds a run that ended
    unfinished (``ended_unfinished``) and saved no checkpoint, and every one of them is a file nerfexp
    wrote by the directory's manifest (``nerfexp.manifest.check_ours``). None where it holds the run that
    ``resume`` (a checkpoint inside it) continues, the files that run writes over (``RUN_REWRITES``) are its
    own, and it is not training now in a process of this host: the directory is that run's already.
    Otherwise a NerfexpError saying what it holds and what to do: files where it holds no run
    (``held_run``), files nerfexp cannot show it wrote (named; a directory of an earlier nerfexp, without a
    manifest, says so), or another run (continued with ``resume=`` one of its checkpoints, where it
    saved one: ``saved_checkpoints``)."""
    held = held_run(run_dir)
    entries = [entry for entry in folder_entries(run_dir) if entry not in manifest.BOOKKEEPING]
    if held is None:
        if foreign := [entry for entry in entries if not is_made(entry, CLAIM_DRAFTS)]:
            raise NerfexpError(foreign_message(run_dir, foreign, "nerfexp",
                                               "choose a new or empty directory (hydra.run.dir=...)"))
        return []
    if resume is not None and run_dir.resolve() in Path(resume).resolve().parents:
        if (state := read_state(run_dir)) is not None and state.here:
            raise NerfexpError(f"{run_dir} holds {held}, still training ({state.detail}): continuing it there while "
                               "it runs would have two runs write one directory; wait for it to end, or stop it, "
                               f"then resume={resume} hydra.run.dir={run_dir}")
        check_run_files(run_dir, held, [entry for entry in entries if is_made(entry, RUN_REWRITES)],
                        f"or continue it in another directory (resume={resume} hydra.run.dir=...)")
        return None
    if checkpoints := saved_checkpoints(run_dir):
        raise NerfexpError(f"{run_dir} holds {held}: continue it with resume={checkpoints[0]} "
                           f"hydra.run.dir={run_dir}, or choose another directory (hydra.run.dir=...)")
    if not ended_unfinished(run_dir):
        raise NerfexpError(f"{run_dir} holds {held}: choose another directory (hydra.run.dir=...)")
    check_run_files(run_dir, held, entries, "or choose another directory (hydra.run.dir=...)")
    return entries


def check_run_files(run_dir: Path, held: str, entries: list[str], alternative: str) -> None:
    """A NerfexpError where one of ``entries`` of ``run_dir``, which the run starting would write over or
    remove, is not a file nerfexp wrote by the directory's manifest (``nerfexp.manifest.check_ours``); where
    the directory has no manifest (a run of an earlier nerfexp), one saying so. Both end in ``alternative``."""
    if entries and not os.path.lexists(run_dir / manifest.MANIFEST):
        raise NerfexpError(f"{run_dir} holds {held} of an earlier nerfexp, which kept no record of the files it "
                           f"wrote (no {manifest.MANIFEST}), so nothing in it is removed or written over: move "
                           f"its files elsewhere yourself, {alternative}")
    manifest.check_ours(run_dir, entries, "nerfexp", f"move {{it}} elsewhere, {alternative}")


def remove_entries(folder: Path, entries: list[str]) -> None:
    """Delete ``entries`` (``/``-separated paths relative to ``folder``), then the folders they leave
    empty inside ``folder``: nothing else; their records in the folder's manifest go with them."""
    emptied = set()
    for entry in entries:
        (folder / entry).unlink(missing_ok=True)
        emptied.update(Path(entry).parents)
    for parent in sorted(emptied - {Path(".")}, key=lambda path: len(path.parts), reverse=True):
        with contextlib.suppress(OSError):  # a folder that still holds something stays
            (folder / parent).rmdir()
    manifest.record(folder, entries)


class RunDirectoryGuard(Callback):
    """Hydra callback: a run starts only in a directory of its own, checked before Hydra writes its
    config there (``hydra.callbacks.run_directory``): nothing a user made is written over.

    A single run stops with one line (exit status 1) unless ``hydra.run.dir`` is new or empty, holds the
    run that ``resume`` continues, or holds a run that ended unfinished and saved no checkpoint, whose
    files are then removed where each is one nerfexp wrote, saying so in one line (``admit_run``); then it
    claims the directory
    (``claim``). A multirun stops unless ``hydra.sweep.dir`` is new or empty.
    In a distributed job started by SLURM every process runs this; global rank 0 checks and claims.
    It stops with ``SystemExit``, whatever the check raised (``nerfexp.errors.callback_refusals``): Hydra turns a
    callback's exceptions into warnings and goes on."""

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        if not is_global_zero():
            return
        run_dir = Path(config.hydra.run.dir)
        with callback_refusals("the run directory's check"):
            try:
                replaced = admit_run(run_dir, config.get("resume"))
                if replaced is None:  # the run continued
                    return
                if replaced:
                    print(f"nerfexp: {run_dir} holds a run that ended unfinished and saved no checkpoint: replacing "
                          f"it, removing its {len(replaced)} files ({', '.join(replaced[:3])}"
                          f"{', ...' * (len(replaced) > 3)})", file=sys.stderr)
                    remove_entries(run_dir, replaced)
                if not claim(run_dir, list(config.hydra.overrides.task)):
                    raise NerfexpError(f"{run_dir} holds a run that started at the same time: choose another "
                                       "directory (hydra.run.dir=...)")
            except OSError as error:
                raise SystemExit(f"nerfexp: error: cannot write the run directory {run_dir}: {error.strerror} "
                                 "(choose another with hydra.run.dir=...)") from None

    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        with callback_refusals("the sweep directory's check"):
            try:
                sweep_dir.mkdir(parents=True, exist_ok=True)
                tempfile.TemporaryFile(dir=sweep_dir).close()  # writable, before any job starts
            except OSError as error:
                raise SystemExit(f"nerfexp: error: cannot write the sweep directory {sweep_dir}: {error.strerror} "
                                 "(choose another with hydra.sweep.dir=...)") from None
            runs = find_run_dirs(sweep_dir)
            if runs:
                raise SystemExit(f"nerfexp: error: {sweep_dir} holds the runs of an earlier sweep ({len(runs)}): "
                                 "choose another directory (hydra.sweep.dir=...)")
            if entries := folder_entries(sweep_dir):
                raise SystemExit("nerfexp: error: " + foreign_message(
                    sweep_dir, entries, "this sweep", "choose a new or empty directory (hydra.sweep.dir=...)"))
