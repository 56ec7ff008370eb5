"""The kernel cache: a kernel is loaded only where it is the build nerfexp made, on this machine, of these
sources with this compiler, torch and CPU; anything else is rebuilt, or the torch path runs.

A built kernel is a Python extension module: importing it runs its code. So nerfexp never imports a file by
its name in a cache. It builds each kernel into a folder of its own, ``ROOT/nerfexp/NAME-KEY`` (ROOT: torch's
extension cache, ``TORCH_EXTENSIONS_DIR`` or ``~/.cache/torch_extensions``; KEY: the SHA-256 of what it is
built from, ``built_from``), and writes ``record.json`` beside the library: what it was built from, the
library's SHA-256, and the inode and change time its file got when it was written. Before a later run imports
it (from that exact file), ``checked_build`` asks that

- every folder above the cache is owned by this user or root and writable by nobody else (or sticky, as
  ``/tmp``), and the cache's own folders and files are this user's, writable by this user alone: no one else
  can have put or changed a file in it;
- the record is there, bounded, well-typed, and says the build is of the same sources, flags, compiler, torch,
  Python and CPU;
- the library is a regular file with the record's inode, change time and SHA-256: a truncated, changed or
  planted file fails, and so does one copied in from another cache (a copy is a new inode with a new change
  time, which no user can set), so a cache brought from elsewhere is rebuilt here, never run.

A build that fails a check is rebuilt (``build``: in a new folder, renamed over the old one once it is
whole, so a killed build leaves no half of one); a cache another user could write is not used at all (the
torch path). Builds of one kernel are one at a time, under an ``fcntl.flock`` of ``NAME-KEY.lock``: a lock
is held only by a live process (a killed build's lock file holds none and is taken at once), which writes its
process id and host into the file as it takes it. A process that finds the lock held says so at once, in a line
naming the file, the process holding it and the longest it will wait, and again every ``LOCK_SAY_S`` while it
waits (``build_lock``); one held for longer than ``BUILD_LIMIT`` is given up on with a line naming the file, never
waited on without end. A build says so as it starts (it takes about a minute).
"""

import contextlib
import fcntl
import hashlib
import importlib.util
import json
import logging
import os
import platform
import re
import shutil
import socket
import stat
import subprocess
import sysconfig
import time
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

from nerfexp.files import atomic_directory, atomic_write
from nerfexp.reading import UnreadableFile, read_json, sha256

CACHE_FOLDER = "nerfexp"  # under the cache root: nerfexp's builds, one folder per kernel and what it is built from
RECORD = "record.json"  # beside the library: what it was built from, its SHA-256, inode and change time
RECORD_BYTES = 64 << 10  # a record is a few hundred bytes
# On x86-64, the vector instructions of the CPU it is built on (the CPU is in the key: a build runs only where it was
# made) without fused multiply-adds (which round once where the C++ rounds twice): the results of the baseline
# architecture's build, bit for bit, in loops over blocks of positions that its vector units run several at a time
NATIVE = ("-march=native", "-ffp-contract=off") if platform.machine() in ("x86_64", "AMD64") else ()
CFLAGS = ("-O3", "-fopenmp", *NATIVE)
LDFLAGS = ("-fopenmp",)
LIBRARY_SUFFIX = ".so"  # torch's name for the library it builds, NAME.so, on every POSIX system
BUILD_LIMIT = 20 * 60  # seconds: a build takes about a minute on 2 cores; a lock held 20 times that is not a build
LOCK_POLL = 0.5  # seconds between tries of a held lock
LOCK_SAY_S = 60  # seconds between the lines of a wait for a held lock (the first is said at once)
HOLDER_BYTES = 256  # the most read of a lock file: its holder's "PID HOST" line
COMPILER_SECONDS = 60  # for ``CXX --version``: a compiler that does not answer in a minute builds nothing
UNSHARED = stat.S_IWGRP | stat.S_IWOTH  # write permission for anyone but the owner

log = logging.getLogger(__name__)


class NotBuilt(Exception):
    """Why a kernel cannot be used here, in a phrase for the one log line after which the torch path runs."""


class FailedCheck(Exception):
    """Why a cached build is not the one nerfexp built (``checked_build``): it is rebuilt."""


def cache_root() -> Path:
    """Torch's extension cache, absolute: ``TORCH_EXTENSIONS_DIR``, else torch's ``~/.cache/torch_extensions``."""
    from torch.utils.cpp_extension import get_default_build_root

    return Path(os.path.abspath(os.environ.get("TORCH_EXTENSIONS_DIR") or get_default_build_root()))


def cpu() -> str:
    """This CPU as a compiler sees it: its architecture and the SHA-256 of its feature flags (``/proc/cpuinfo``'s
    first ``flags`` or ``Features`` line; the processor's name where there is no such file)."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        lines = [platform.processor()]
    features = next((line.split(":", 1)[1].split() for line in lines if re.match(r"(flags|Features)\s*:", line)),
                    lines[:1])
    return f"{platform.machine()} {hashlib.sha256(' '.join(sorted(features)).encode()).hexdigest()}"


def compiler() -> str:
    """The C++ compiler torch builds with (``CXX``, else ``c++``): its resolved path and ``--version``'s first
    line; ``NotBuilt`` where there is none that answers."""
    from torch.utils.cpp_extension import get_cxx_compiler

    name = get_cxx_compiler()
    found = shutil.which(name)
    if found is None:
        raise NotBuilt(f"no C++ compiler: {name} not found")
    try:
        answer = subprocess.run([found, "--version"], capture_output=True, text=True, timeout=COMPILER_SECONDS,
                                check=True).stdout
    except (OSError, subprocess.SubprocessError) as error:
        raise NotBuilt(f"the C++ compiler {found} does not answer --version ({type(error).__name__})") from None
    return f"{os.path.realpath(found)} {(answer.splitlines() or [''])[0]}"


def built_from(name: str, source: bytes) -> dict:
    """What the kernel ``name`` is built from: its source's SHA-256, the flags, compiler, torch, Python (its
    extension modules' suffix) and CPU. A build of anything else is another build."""
    import torch

    return {"kernel": name, "source_sha256": hashlib.sha256(source).hexdigest(), "cflags": list(CFLAGS),
            "ldflags": list(LDFLAGS), "compiler": compiler(), "torch": torch.__version__,
            "python": sysconfig.get_config_var("EXT_SUFFIX"), "cpu": cpu()}


def build_folder(cache: Path, expected: dict) -> Path:
    """The folder of the build ``expected`` (``built_from``) in nerfexp's ``cache`` (``private_cache``):
    ``NAME-KEY``, KEY the start of the SHA-256 of what it is built from."""
    key = hashlib.sha256(json.dumps(expected, sort_keys=True).encode()).hexdigest()[:16]
    return cache / f"{expected['kernel']}-{key}"


def shared_reason(path: Path, found: os.stat_result, own: bool) -> str | None:
    """Why another user could write in the folder or file ``path`` (its ``lstat``), or None. ``own``: one
    nerfexp makes (this user's, writable by this user alone); else a folder above the cache (this user's or
    root's, and writable by nobody else unless sticky, where no one removes or renames another's entries)."""
    owners = (os.geteuid(),) if own else (os.geteuid(), 0)
    if found.st_uid not in owners:
        return f"{path} is owned by user id {found.st_uid}, not by you"
    if found.st_mode & UNSHARED and (own or not found.st_mode & stat.S_ISVTX):
        return f"{path} is writable by others (mode {stat.S_IMODE(found.st_mode):04o})"
    return None


def private_cache(root: Path) -> Path:
    """``ROOT/nerfexp``, made where missing (mode 0700), once every folder from ``/`` to it is one that only
    this user (or root) can write: ``NotBuilt`` otherwise, naming the folder and what to do."""
    cache = Path(os.path.realpath(root)) / CACHE_FOLDER
    for folder in reversed((cache, *cache.parents)):  # from the top: a folder is made only in one checked first
        if not os.path.lexists(folder):
            with contextlib.suppress(FileExistsError):  # another process made it meanwhile: checked all the same
                os.mkdir(folder, 0o700)
        reason = shared_reason(folder, os.lstat(folder), own=folder == cache)
        if reason is not None:
            raise NotBuilt(f"{reason}: nerfexp builds and loads kernels only where no one else can write "
                           f"(set TORCH_EXTENSIONS_DIR to a folder of your own)")
    return cache


def read_record(folder: Path, expected: dict) -> dict:
    """The record beside the build in ``folder``, where it is one of the build ``expected``: a dict whose
    module is ``nerfexp_NAME`` (``_vN`` where torch renamed a rebuild in one process), whose library is that
    module's file in ``folder``, and whose hash, inode and change time are typed; ``FailedCheck`` otherwise."""
    try:
        record = read_json(folder / RECORD, RECORD_BYTES)
    except UnreadableFile as error:
        raise FailedCheck(str(error)) from None
    typed = {"built_from": dict, "module": str, "library": str, "sha256": str, "inode": int, "changed_ns": int}
    if not isinstance(record, dict) or any(type(record.get(key)) is not kind for key, kind in typed.items()):
        raise FailedCheck(f"{folder / RECORD}: not a record of a nerfexp build")
    if record["built_from"] != expected:
        raise FailedCheck(f"{folder / RECORD}: built from other sources, flags, compiler, torch or CPU")
    if (not re.fullmatch(rf"nerfexp_{re.escape(expected['kernel'])}(_v\d+)?", record["module"])
            or record["library"] != record["module"] + LIBRARY_SUFFIX):
        raise FailedCheck(f"{folder / RECORD}: names module {record['module']!r} in {record['library']!r}, not "
                          f"nerfexp_{expected['kernel']}'s library")
    return record


def checked_build(folder: Path, expected: dict) -> tuple[str, Path] | None:
    """The module name and library of the build in ``folder`` where it is the one nerfexp built there of
    ``expected`` (the module docstring's checks), nothing imported; None where there is no build; ``FailedCheck``
    naming the file and what is wrong otherwise."""
    try:
        found = os.lstat(folder)
    except FileNotFoundError:
        return None
    if not stat.S_ISDIR(found.st_mode):
        raise FailedCheck(f"{folder} is not a folder")
    reason = shared_reason(folder, found, own=True)
    if reason is not None:
        raise FailedCheck(reason)
    record = read_record(folder, expected)
    library = folder / record["library"]
    try:
        found = os.lstat(library)
    except FileNotFoundError:
        raise FailedCheck(f"{library} is missing") from None
    if not stat.S_ISREG(found.st_mode):
        raise FailedCheck(f"{library} is not a regular file")
    reason = shared_reason(library, found, own=True)
    if reason is not None:
        raise FailedCheck(reason)
    if (found.st_ino, found.st_ctime_ns) != (record["inode"], record["changed_ns"]):
        raise FailedCheck(f"{library} is not the file nerfexp wrote there (copied, replaced or changed since)")
    if sha256(library) != record["sha256"]:
        raise FailedCheck(f"{library}: its SHA-256 is not its record's (truncated or changed)")
    return record["module"], library


def import_library(module: str, library: Path) -> ModuleType:
    """The extension module ``module`` imported from the file ``library`` itself (never looked up by name)."""
    spec = importlib.util.spec_from_file_location(module, library)
    try:
        loaded = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(loaded)
    except ImportError as error:  # a library built for another system's libraries: one line, the torch path
        raise NotBuilt(f"{library} cannot be imported ({error})") from None
    return loaded


def holder_record() -> bytes:
    """What a process writes into a build lock as it takes it: its process id and host, ``PID HOST``."""
    return f"{os.getpid()} {socket.gethostname()}\n".encode()


def process_running(pid: int) -> bool:
    """Whether a process ``pid`` runs on this machine (one of another user's too)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # there, and another user's
        return True
    return True


def holder_text(record: bytes) -> str:
    """The process holding a build lock, in words, from what its holder wrote in it (``holder_record``):
    ``process PID`` (``on HOST`` where that is another machine's name); where the file names no process that runs
    here (one that took the lock and has not written yet, or a program other than nerfexp), it says so.

    >>> holder_text(f"1 {socket.gethostname()}\\n".encode()), holder_text(b"12 elsewhere\\n"), holder_text(b"")
    ('process 1', 'process 12 on elsewhere', 'another process (the lock file names none)')
    """
    fields = record.decode("ascii", "replace").split()
    if len(fields) != 2 or not fields[0].isdigit() or int(fields[0]) == 0:
        return "another process (the lock file names none)"
    pid, host = int(fields[0]), fields[1]
    if host != socket.gethostname():
        return f"process {pid} on {host}"
    if process_running(pid):
        return f"process {pid}"
    return f"another process (the lock file names process {pid}, which is not running)"


def minutes_text(seconds: float) -> str:
    """A wait in words: whole seconds under two minutes, else whole minutes.

    >>> minutes_text(42.4), minutes_text(119), minutes_text(1140)
    ('42 s', '119 s', '19 min')
    """
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.0f} min"


def waiting_line(name: str, path: Path, holder: str, held_s: float, waited_s: float) -> str:
    """The line a process waiting for the build lock ``path`` of kernel ``name`` says (at once, and every
    ``LOCK_SAY_S``): who holds it (``holder_text``), for how long it has, and the longest this process waits yet
    (``BUILD_LIMIT`` less ``held_s``), after which the torch path runs."""
    left = minutes_text(max(0.0, BUILD_LIMIT - held_s))
    if waited_s == 0:
        return (f"kernel {name}: waiting for {holder}, which holds its build lock {path} (for {minutes_text(held_s)} "
                f"so far: building it), at most {left} more, then the torch path runs")
    return (f"kernel {name}: still waiting for {holder} ({path}), {minutes_text(waited_s)} so far, at most {left} "
            f"more")


@contextlib.contextmanager
def build_lock(path: Path, name: str) -> Iterator[None]:
    """Inside the block this process alone builds the kernel ``name`` whose lock is ``path`` (an exclusive
    ``flock``, released by the system when its process ends, however it ends), its process id and host written in
    the file (``holder_record``). Where another process holds it, one line says so at once and one every
    ``LOCK_SAY_S`` after (``waiting_line``), and one when it is taken. A lock held for longer than ``BUILD_LIMIT``
    (its file's age: the holder touches it as it takes it) is ``NotBuilt`` naming the file."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o600)
    try:
        started, said = time.monotonic(), None
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                held = time.time() - os.fstat(fd).st_mtime
                if held > BUILD_LIMIT:
                    raise NotBuilt(f"{path} has been held by another process for {held / 60:.0f} min, longer than "
                                   f"a build takes ({BUILD_LIMIT // 60} min): if no nerfexp build is running, "
                                   f"remove it") from None
                waited = time.monotonic() - started
                if said is None or waited - said >= LOCK_SAY_S:
                    holder = holder_text(os.pread(fd, HOLDER_BYTES, 0))
                    log.info("%s", waiting_line(name, path, holder, held, 0.0 if said is None else waited))
                    said = waited
                time.sleep(LOCK_POLL)
        if said is not None:
            log.info("kernel %s: build lock %s taken after %s of waiting", name, path,
                     minutes_text(time.monotonic() - started))
        os.ftruncate(fd, 0)
        os.pwrite(fd, holder_record(), 0)
        os.utime(fd)  # its age is how long this build has held it
        yield
    finally:
        os.close(fd)  # releases the lock


def build(folder: Path, source: bytes, expected: dict) -> ModuleType:
    """The kernel built by torch's ``cpp_extension.load`` from ``source`` (the bytes hashed into ``expected``,
    written into the new folder and compiled there) into a new folder renamed to ``folder`` once whole, with
    its record; the module torch imported from the new build. Called under ``build_lock``: the folders a killed
    build of it left (``nerfexp.files.atomic_directory``'s ``.NAME-KEY.*.tmp`` and ``.old``) are removed first."""
    from torch.utils.cpp_extension import load

    for left in (*folder.parent.glob(f".{folder.name}.*.tmp"), *folder.parent.glob(f".{folder.name}.*.old")):
        shutil.rmtree(left, ignore_errors=True)
    name = expected["kernel"]
    with atomic_directory(folder, replace=True) as new:
        atomic_write(new / f"{name}.cpp", source)
        module = load(f"nerfexp_{name}", [str(new / f"{name}.cpp")], extra_cflags=list(CFLAGS),
                      extra_ldflags=list(LDFLAGS), build_directory=str(new), verbose=False)
        (library,) = new.glob(f"*{LIBRARY_SUFFIX}")  # the one torch linked, named for its module (not
        # module.__file__: a process that holds a module of that name already is handed that one by Python)
        found = os.lstat(library)
        record = {"built_from": expected, "module": library.name.removesuffix(LIBRARY_SUFFIX), "library": library.name,
                  "sha256": sha256(library), "inode": found.st_ino, "changed_ns": found.st_ctime_ns}
        atomic_write(new / RECORD, json.dumps(record, indent=1).encode())
    return module


def check(folder: Path, expected: dict) -> tuple[tuple[str, Path] | None, str | None]:
    """``checked_build``'s answer, and why it failed (None where it did not)."""
    try:
        return checked_build(folder, expected), None
    except FailedCheck as error:
        return None, str(error)


def cached_kernel(name: str, source: bytes) -> tuple[ModuleType, bool, str | None]:
    """The kernel ``name`` built from ``source``: imported from the cache where its build passes
    ``checked_build``, else built now; whether it was built now; and why the cached build it replaced failed its
    check (None where there was none). ``NotBuilt`` where it cannot be had here, a file that cannot be made or
    read in the cache included."""
    try:
        return _cached_kernel(name, source)
    except OSError as error:
        raise NotBuilt(f"{error.filename or 'the kernel cache'}: {error.strerror or error}") from None


def _cached_kernel(name: str, source: bytes) -> tuple[ModuleType, bool, str | None]:
    """``cached_kernel``, an OSError of the cache's files raised as it is."""
    expected = built_from(name, source)
    folder = build_folder(private_cache(cache_root()), expected)
    found, _ = check(folder, expected)
    if found is None:
        with build_lock(folder.with_name(f"{folder.name}.lock"), name):
            found, failed = check(folder, expected)  # again: another process may have built it meanwhile
            if found is None:
                log.info("kernel %s: building it in %s (about a minute, once per machine and source)%s", name,
                         folder, "" if failed is None else f": its cached build failed a check: {failed}")
                try:
                    module = build(folder, source, expected)
                except Exception as error:  # no ninja, a failed compile, a full disk
                    text = str(error).strip()
                    reason = text.splitlines()[-1] if text else type(error).__name__
                    raise NotBuilt(reason if failed is None else f"{reason}; its cached build failed a check: "
                                   f"{failed}") from None
                return module, True, failed
    return import_library(*found), False, None
