"""The kernel cache (src/nerfexp/kernels/cache.py) imports only the build nerfexp made here: one real build of the
lazy Adam kernel (the smaller one) into a cache of the test's own, and copies of it damaged as a careless or
hostile user would (truncated, planted, copied from elsewhere, a forged or broken record, folders others can
write, a lock left by a killed build); the switch ``NERFEXP_KERNELS`` read as a boolean word or refused."""

import hashlib
import json
import os
import re
import shutil
import socket
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from hypothesis import assume, given
from hypothesis import strategies as st
from torch.utils.cpp_extension import get_cxx_compiler, is_ninja_available

from nerfexp import kernels
from nerfexp.errors import ConfigError
from nerfexp.kernels import cache
from nerfexp.training.module import NeRFModule
from tests.helpers import TINY, run_nerfexp
from tests.kernels.adam_step import adam_rows

NAME = "lazy_adam"
SOURCE = (Path(kernels.__file__).parent / f"{NAME}.cpp").read_bytes()
needs_compiler = pytest.mark.skipif(shutil.which(get_cxx_compiler()) is None or not is_ninja_available(),
                                    reason="no C++ compiler, or no ninja, to build the kernel with")


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """The lazy Adam kernel built once by ``cached_kernel`` into a cache of its own: (cache root, the module)."""
    root = tmp_path_factory.mktemp("extensions")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("TORCH_EXTENSIONS_DIR", str(root))
        module, now, failed = cache.cached_kernel(NAME, SOURCE)
    assert now and failed is None
    return root, module


def copied(built, to: Path) -> tuple[Path, Path]:
    """A copy of the built cache under ``to`` (root, the build's folder) whose record names the copy's own
    inode and change time, as nerfexp's record of a build made there would: it passes every check."""
    root, _ = built
    shutil.copytree(root / cache.CACHE_FOLDER, to / cache.CACHE_FOLDER)
    (folder,) = [path for path in (to / cache.CACHE_FOLDER).iterdir() if path.is_dir()]
    rerecord(folder)
    return to, folder


def rerecord(folder: Path) -> None:
    """Set the record's inode and change time to its library's (as if nerfexp had written the file as it is)."""
    record = json.loads((folder / cache.RECORD).read_text())
    found = os.lstat(folder / record["library"])
    record.update(inode=found.st_ino, changed_ns=found.st_ctime_ns)
    (folder / cache.RECORD).write_text(json.dumps(record))


def library(folder: Path) -> Path:
    return folder / json.loads((folder / cache.RECORD).read_text())["library"]


def expected() -> dict:
    return cache.built_from(NAME, SOURCE)


LATER = """
import json, logging, sys
logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(name)s: %(message)s")
from nerfexp.kernels import kernel
from tests.kernels.adam_step import adam_rows
module = kernel("lazy_adam")
print(json.dumps([module.__file__, adam_rows(module).tolist()]))
"""


@needs_compiler
def test_a_build_is_recorded_and_a_later_process_imports_that_file_after_its_checks(built):
    root, module = built
    (folder,) = [path for path in (root / cache.CACHE_FOLDER).iterdir() if path.is_dir()]
    record = json.loads((folder / cache.RECORD).read_text())
    assert record["built_from"] == expected()
    assert record["built_from"]["source_sha256"] == hashlib.sha256(SOURCE).hexdigest()
    assert record["sha256"] == hashlib.sha256(library(folder).read_bytes()).hexdigest()
    found = os.lstat(library(folder))
    assert (record["inode"], record["changed_ns"]) == (found.st_ino, found.st_ctime_ns)
    assert (folder / f"{NAME}.cpp").read_bytes() == SOURCE  # the bytes hashed are the bytes compiled
    assert folder == cache.build_folder(root / cache.CACHE_FOLDER, expected())
    # Adam's first step moves each touched value by lr (m / sqrt(v) = 1 after bias correction): 1 - 0.1
    assert torch.allclose(adam_rows(module), torch.tensor([[0.9] * 3, [1.0] * 3, [0.9] * 3, [1.0] * 3]))
    # a later process imports that file, after its checks, without building
    later = subprocess.run([sys.executable, "-c", LATER], capture_output=True, text=True, timeout=300,
                           env={**os.environ, "TORCH_EXTENSIONS_DIR": str(root)})
    assert later.returncode == 0, later.stderr[-3000:]
    assert not [line for line in later.stderr.splitlines() if line.startswith("nerfexp.kernels")]
    assert json.loads(later.stdout) == [str(library(folder)), adam_rows(module).tolist()]


def truncate(folder: Path) -> None:
    lib = library(folder)
    lib.write_bytes(lib.read_bytes()[: lib.stat().st_size // 2])


def plant(folder: Path) -> None:  # another library in its place (a copy of another extension module)
    shutil.copyfile(torch._C.__file__, library(folder))


def corrupt_unseen(folder: Path) -> None:  # a byte changed where the file system keeps no trace of it
    lib = library(folder)
    data = bytearray(lib.read_bytes())
    data[len(data) // 2] ^= 0xFF
    lib.write_bytes(bytes(data))
    rerecord(folder)


def forge_module(folder: Path) -> None:  # the record names another module: one the import would look for
    record = json.loads((folder / cache.RECORD).read_text())
    record.update(module="os", library="os.so")
    (folder / cache.RECORD).write_text(json.dumps(record))


def forge_path(folder: Path) -> None:  # the record names a library outside its folder
    record = json.loads((folder / cache.RECORD).read_text())
    record.update(library="../../nerfexp_lazy_adam.so")
    (folder / cache.RECORD).write_text(json.dumps(record))


def other_source(folder: Path) -> None:  # a build of other sources (an older nerfexp's) under this key
    record = json.loads((folder / cache.RECORD).read_text())
    record["built_from"]["source_sha256"] = "0" * 64
    (folder / cache.RECORD).write_text(json.dumps(record))


def no_record(folder: Path) -> None:
    (folder / cache.RECORD).unlink()


def huge_record(folder: Path) -> None:
    (folder / cache.RECORD).write_bytes(b" " * (cache.RECORD_BYTES + 1))


def link_library(folder: Path) -> None:  # the library a link to a file elsewhere
    lib = library(folder)
    elsewhere = folder.parent.parent / "elsewhere.so"
    lib.rename(elsewhere)
    lib.symlink_to(elsewhere)


def shared_folder(folder: Path) -> None:
    folder.chmod(0o777)


def shared_library(folder: Path) -> None:
    library(folder).chmod(0o775)


DAMAGES = {  # how a build was damaged -> what the refusal says
    truncate: "is not the file nerfexp wrote there",
    plant: "is not the file nerfexp wrote there",
    corrupt_unseen: "its SHA-256 is not its record's",
    forge_module: "names module 'os'",
    forge_path: "names module",
    other_source: "built from other sources",
    no_record: "record.json: cannot be read",
    huge_record: "larger than",
    link_library: "is not a regular file",
    shared_folder: "is writable by others (mode 0777)",
    shared_library: "is writable by others (mode 0775)",
}


@needs_compiler
@pytest.mark.parametrize("damage", DAMAGES, ids=lambda damage: damage.__name__)
def test_a_damaged_or_foreign_build_fails_its_check_before_anything_is_imported(damage, built, tmp_path):
    _, folder = copied(built, tmp_path)
    assert cache.checked_build(folder, expected()) == (json.loads((folder / cache.RECORD).read_text())["module"],
                                                       library(folder))
    damage(folder)
    with pytest.raises(cache.FailedCheck) as failed:
        cache.checked_build(folder, expected())
    assert DAMAGES[damage] in str(failed.value) and "\n" not in str(failed.value) and str(folder) in str(failed.value)


@needs_compiler
def test_a_cache_copied_from_elsewhere_is_rebuilt_here_never_run(built, tmp_path):
    # a copy (another machine's cache, a colleague's tarball, a restore) holds new inodes with new change times
    root, _ = built
    shutil.copytree(root / cache.CACHE_FOLDER, tmp_path / cache.CACHE_FOLDER)
    (folder,) = [path for path in (tmp_path / cache.CACHE_FOLDER).iterdir() if path.is_dir()]
    with pytest.raises(cache.FailedCheck, match="not the file nerfexp wrote there"):
        cache.checked_build(folder, expected())


@needs_compiler
@pytest.mark.skipif(os.geteuid() != 0, reason="only root can give a file to another user")
def test_a_build_owned_by_another_user_fails_its_check(built, tmp_path):
    _, folder = copied(built, tmp_path)
    os.chown(library(folder), 1234, 1234)
    rerecord(folder)  # chown changes the change time: the record follows, only the owner is wrong
    with pytest.raises(cache.FailedCheck, match=r"is owned by user id 1234, not by you"):
        cache.checked_build(folder, expected())


JSON = st.recursive(st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=8),
                    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=8), inner, max_size=3),
                    max_leaves=12)


@needs_compiler
@given(record=JSON)
def test_any_other_record_fails_its_check(built, tmp_path_factory, record):
    # a record nerfexp did not write, whatever it holds, is one line: never a pass, never another error
    _, folder = copied(built, tmp_path_factory.mktemp("copy"))
    (folder / cache.RECORD).write_text(json.dumps(record))
    with pytest.raises(cache.FailedCheck) as failed:
        cache.checked_build(folder, expected())
    assert "\n" not in str(failed.value)


@needs_compiler
@given(field=st.sampled_from(["built_from", "module", "library", "sha256", "inode", "changed_ns"]), value=JSON)
def test_a_record_with_any_field_changed_fails_its_check(built, tmp_path_factory, field, value):
    _, folder = copied(built, tmp_path_factory.mktemp("copy"))
    record = json.loads((folder / cache.RECORD).read_text())
    assume(value != record[field])
    record[field] = value
    (folder / cache.RECORD).write_text(json.dumps(record))
    with pytest.raises(cache.FailedCheck) as failed:
        cache.checked_build(folder, expected())
    assert "\n" not in str(failed.value)


def test_each_thing_a_kernel_is_built_from_names_another_build_folder(tmp_path, monkeypatch):
    # another compiler (CXX, its --version), source, flag, torch, Python or CPU: another folder, never a stale build
    fake = tmp_path / "g++"
    fake.write_text("#!/bin/sh\necho 'g++ (a compiler of its own) 99.1'\n")
    fake.chmod(0o755)
    monkeypatch.setenv("CXX", str(fake))
    built_from = cache.built_from(NAME, SOURCE)
    assert built_from["compiler"] == f"{fake} g++ (a compiler of its own) 99.1"
    assert built_from["torch"] == torch.__version__ and built_from["cpu"] == cache.cpu()
    folder = cache.build_folder(tmp_path, built_from)
    assert folder.parent == tmp_path and folder.name.startswith(f"{NAME}-")
    for key, value in built_from.items():
        assert cache.build_folder(tmp_path, {**built_from, key: [value]}) != folder, key
    monkeypatch.setenv("CXX", str(tmp_path / "none"))
    with pytest.raises(cache.NotBuilt, match=f"no C\\+\\+ compiler: {tmp_path / 'none'} not found"):
        cache.built_from(NAME, SOURCE)


PLANTED = "open({marker!r}, 'w').write('ran')\n"


@needs_compiler
def test_a_failed_check_rebuilds_and_modules_planted_by_name_never_run(built, tmp_path, monkeypatch):
    root, folder = copied(built, tmp_path)
    marker = tmp_path / "planted-code-ran"
    for planted in (root / f"nerfexp_{NAME}", root / "py311_cpu" / f"nerfexp_{NAME}", folder):  # torch's names too
        planted.mkdir(parents=True, exist_ok=True)
        (planted / f"nerfexp_{NAME}.py").write_text(PLANTED.format(marker=str(marker)))
    (root / f"nerfexp_{NAME}" / f"nerfexp_{NAME}.so").write_text(PLANTED.format(marker=str(marker)))
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(root))
    module, now, failed = cache.cached_kernel(NAME, SOURCE)  # the genuine build passes: imported, not built
    assert not now and failed is None and torch.equal(adam_rows(module), adam_rows(built[1]))
    shutil.rmtree(root / cache.CACHE_FOLDER)  # never truncate a library this process has loaded: a SIGBUS
    root, folder = copied(built, root)
    truncate(folder)
    rebuilt = []
    monkeypatch.setattr(cache, "build", lambda *args: rebuilt.append(args) or "the rebuilt module")
    module, now, failed = cache.cached_kernel(NAME, SOURCE)
    assert (module, now) == ("the rebuilt module", True) and len(rebuilt) == 1
    assert str(library(folder)) in failed and "not the file nerfexp wrote there" in failed
    assert not marker.exists()


@needs_compiler
def test_a_lock_left_by_a_killed_build_is_taken_at_once(built, tmp_path, monkeypatch):
    root, folder = copied(built, tmp_path)
    lock = folder.with_name(f"{folder.name}.lock")
    lock.touch()  # what a build killed midway leaves: the file, holding no lock
    os.utime(lock, (0, 0))
    truncate(folder)
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(root))
    monkeypatch.setattr(cache, "build", lambda *args: "the rebuilt module")
    started = time.monotonic()
    assert cache.cached_kernel(NAME, SOURCE)[0] == "the rebuilt module"
    assert time.monotonic() - started < cache.LOCK_POLL * 10


@needs_compiler
def test_a_lock_held_longer_than_a_build_takes_is_named_in_one_line_never_waited_on(built, tmp_path, monkeypatch):
    root, folder = copied(built, tmp_path)
    lock = folder.with_name(f"{folder.name}.lock")
    truncate(folder)
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(root))
    monkeypatch.setattr(cache, "build", lambda *args: pytest.fail("built under another process's lock"))
    holder = os.open(lock, os.O_RDWR | os.O_CREAT)  # another open file: its flock excludes this process's
    try:
        cache.fcntl.flock(holder, cache.fcntl.LOCK_EX)
        os.utime(lock, (time.time() - cache.BUILD_LIMIT - 60,) * 2)  # taken 21 minutes ago
        started = time.monotonic()
        with pytest.raises(cache.NotBuilt, match="held by another process for 21 min") as refused:
            cache.cached_kernel(NAME, SOURCE)
        assert time.monotonic() - started < cache.LOCK_POLL * 10
        assert f"{lock}" in str(refused.value) and "remove it" in str(refused.value)
        assert "\n" not in str(refused.value)
    finally:
        os.close(holder)


HOLDER = """
import sys, time
from pathlib import Path
from nerfexp.kernels.cache import build_lock
with build_lock(Path(sys.argv[1]), "lazy_adam"):
    print("held", flush=True)
    ends = time.monotonic() + float(sys.argv[2])
    while time.monotonic() < ends and not Path(sys.argv[3]).exists():
        time.sleep(0.05)
"""  # holds the lazy Adam kernel's build lock ARGV[1] for ARGV[2] seconds, or until the file ARGV[3] exists


def lock_of(root: Path) -> Path:
    """The build lock of the lazy Adam kernel in the cache under ``root`` (made where missing)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("TORCH_EXTENSIONS_DIR", str(root))
        folder = cache.build_folder(cache.private_cache(cache.cache_root()), expected())
    return folder.with_name(f"{folder.name}.lock")


@needs_compiler
def test_a_wait_for_another_process_s_build_is_said_at_once_and_at_intervals_naming_the_lock_and_process(
        tmp_path, monkeypatch, caplog):
    # another process (a real one, taking the lock as nerfexp does) holds the lock for HOLD seconds: this one says
    # at once that it waits, for which lock and process and for how long at most, again every LOCK_SAY_S, and when
    # it takes the lock; then it builds (a stand-in), and the lock names this process
    hold = 3.0
    lock = lock_of(tmp_path)
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path))
    monkeypatch.setattr(cache, "LOCK_SAY_S", 1.0)
    monkeypatch.setattr(cache, "LOCK_POLL", 0.05)
    monkeypatch.setattr(cache, "build", lambda *args: "the module built after the wait")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(lock), str(hold), str(tmp_path / "never")],
                              stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert holder.stdout.readline() == "held\n"
        started = time.time()
        with caplog.at_level("INFO", logger="nerfexp.kernels"):
            module, now, _ = cache.cached_kernel(NAME, SOURCE)
        waited = time.time() - started
    finally:
        holder.kill()
        holder.wait()
    assert (module, now) == ("the module built after the wait", True)
    lines = [(record.created, record.getMessage()) for record in caplog.records
             if record.name == "nerfexp.kernels.cache"]
    waits = [(at, line) for at, line in lines if "waiting for" in line]
    first_at, first = waits[0]
    assert first_at - started < 1.0  # at once, not after a poll interval's worth of silence
    assert first.startswith(f"kernel {NAME}: waiting for process {holder.pid}, which holds its build lock {lock} "
                            f"(for ") and first.endswith(": building it), at most 20 min more, then the torch path "
                                                         "runs")
    again = [line for _, line in waits[1:]]
    assert len(again) >= int(waited) - 1 >= 1, lines  # one a second while it waited, less the first's second
    assert all(line.startswith(f"kernel {NAME}: still waiting for process {holder.pid} ({lock}), ") and
               line.endswith(" so far, at most 20 min more") for line in again), again
    (taken,) = [line for _, line in lines if "taken after" in line]
    assert re.fullmatch(rf"kernel {NAME}: build lock {re.escape(str(lock))} taken after \d s of waiting", taken)
    assert any(line.startswith(f"kernel {NAME}: building it in {lock.with_suffix('')}") for _, line in lines)
    assert lock.read_bytes() == cache.holder_record()  # the lock now names this process


@needs_compiler
def test_a_run_waiting_for_a_build_says_so_on_its_console_and_in_its_log(tmp_path, monkeypatch):
    # the case: a run that needs a kernel while another live process builds it said nothing for up to 20 min
    lock = lock_of(tmp_path / "extensions")
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "extensions"))
    monkeypatch.setattr(cache, "build", lambda *args: object())  # a module nothing calls (the run uses posenc)
    monkeypatch.setattr(NeRFModule, "kernels", lambda self: [NAME])
    monkeypatch.setattr(kernels, "_SPENT", {})
    monkeypatch.setattr(kernels, "_SAID", set())
    monkeypatch.delenv(kernels.SWITCH, raising=False)
    kernels._built.cache_clear()
    release, said = tmp_path / "release", cache.waiting_line
    monkeypatch.setattr(cache, "waiting_line", lambda *args: release.touch() or said(*args))  # once it has waited
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(lock), "120", str(release)], stdout=subprocess.PIPE,
                              text=True, env=env)
    try:
        assert holder.stdout.readline() == "held\n"
        result = run_nerfexp(*TINY, "scale.steps=4", "scale.val_every=2", f"hydra.run.dir={tmp_path / 'run'}",
                             cwd=tmp_path)
    finally:
        holder.kill()
        holder.wait()
        kernels._built.cache_clear()
    assert result.returncode == 0, result.stderr[-3000:]
    waiting = f"kernel {NAME}: waiting for process {holder.pid}, which holds its build lock {lock}"
    for said in (result.stdout, (tmp_path / "run" / "nerfexp.log").read_text()):
        assert waiting in said and f"kernel {NAME}: building it in " in said
        assert f"kernels, before the training clock started: {NAME} built in " in said


def dead_pid() -> int:
    """The id of a process that has ended (and been reaped)."""
    ended = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    return int(ended.stdout)


@pytest.mark.parametrize(("record", "says"), [
    (lambda pid, host: f"{pid} {host}\n", "process {pid}"),
    (lambda pid, host: "4242 another-host\n", "process 4242 on another-host"),
    (lambda pid, host: f"{dead_pid()} {host}\n", "another process (the lock file names process {dead}, which is not "
                                                  "running)"),
    (lambda pid, host: "", "another process (the lock file names none)"),  # taken, not written yet; or not nerfexp's
    (lambda pid, host: "0 host\n", "another process (the lock file names none)"),
    (lambda pid, host: "x\x00\xff", "another process (the lock file names none)"),
])
def test_the_holder_of_a_lock_is_named_as_its_file_records_it_where_that_is_true(record, says):
    written = record(os.getpid(), socket.gethostname())
    dead = written.split()[0] if written.strip() else None
    assert cache.holder_text(written.encode("latin-1")) == says.format(pid=os.getpid(), dead=dead)


@pytest.mark.parametrize(("held_s", "waited_s", "line"), [
    (2.0, 0.0, "kernel k: waiting for process 7, which holds its build lock /c/k.lock (for 2 s so far: building it), "
               "at most 20 min more, then the torch path runs"),
    (600.0, 0.0, "kernel k: waiting for process 7, which holds its build lock /c/k.lock (for 10 min so far: "
                 "building it), at most 10 min more, then the torch path runs"),
    (660.0, 60.0, "kernel k: still waiting for process 7 (/c/k.lock), 60 s so far, at most 9 min more"),
    (1300.0, 300.0, "kernel k: still waiting for process 7 (/c/k.lock), 5 min so far, at most 0 s more"),
])
def test_a_wait_says_the_longest_it_will_go_on(held_s, waited_s, line):
    # 20 min (BUILD_LIMIT) less how long the lock has been held: then the torch path
    assert cache.waiting_line("k", Path("/c/k.lock"), "process 7", held_s, waited_s) == line


def test_a_cache_others_can_write_is_refused_and_a_sticky_one_above_it_is_not(tmp_path):
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    with pytest.raises(cache.NotBuilt, match=rf"{shared} is writable by others \(mode 0777\): .*TORCH_EXTENSIONS_DIR"):
        cache.private_cache(shared)
    assert not (shared / cache.CACHE_FOLDER).exists()
    shared.chmod(0o1777)  # as /tmp: others may add entries, never move or remove this user's
    made = cache.private_cache(shared / "mine")
    assert made == shared / "mine" / cache.CACHE_FOLDER
    assert all(stat.S_IMODE(os.lstat(folder).st_mode) == 0o700 for folder in (made, made.parent))
    (made / "loose").mkdir()
    made.chmod(0o770)
    with pytest.raises(cache.NotBuilt, match=rf"{made} is writable by others \(mode 0770\)"):
        cache.private_cache(shared / "mine")


@pytest.mark.skipif(os.geteuid() != 0, reason="only root can give a folder to another user")
def test_a_cache_under_another_users_folder_is_refused(tmp_path):
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    os.chown(theirs, 1234, 1234)
    with pytest.raises(cache.NotBuilt, match=rf"{theirs} is owned by user id 1234, not by you"):
        cache.private_cache(theirs / "cache")


NO_NINJA = """
import json, logging, sys, torch
logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(name)s: %(message)s")
from nerfexp.kernels import kernel
print(json.dumps(kernel("lazy_adam") is not None))
"""


@needs_compiler
def test_a_truncated_build_is_one_line_and_the_torch_path_never_a_crash(built, tmp_path):
    # the case: a truncated library in the cache, imported, was a SIGBUS with no line. Here the rebuild
    # fails too (the compiler is there, ninja is not), so the process says both in one line and runs on
    root, folder = copied(built, tmp_path)
    truncate(folder)
    bin_ = tmp_path / "bin"
    bin_.mkdir()
    (bin_ / "c++").symlink_to(shutil.which(get_cxx_compiler()))
    env = {**os.environ, "TORCH_EXTENSIONS_DIR": str(root), "PATH": str(bin_), "CXX": "c++"}
    result = subprocess.run([sys.executable, "-c", NO_NINJA], capture_output=True, text=True, timeout=300, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    said = [line for line in result.stderr.splitlines() if line.startswith("nerfexp.kernels:")]
    assert len(said) == 1, result.stderr[-3000:]
    (building,) = [line for line in result.stderr.splitlines() if line.startswith("nerfexp.kernels.cache:")]
    assert f"kernel lazy_adam: building it in {folder} (" in building  # said as it starts: it takes a minute
    assert "kernel lazy_adam not built (" in said[0] and "torch path runs instead" in said[0]
    assert f"its cached build failed a check: {library(folder)} is not the file nerfexp wrote there" in said[0]
    assert json.loads(result.stdout) is False


SWITCH_ON = ["on", "true", "yes", "1"]
SWITCH_OFF = ["off", "false", "no", "0"]


@given(word=st.sampled_from(SWITCH_ON + SWITCH_OFF), cases=st.lists(st.booleans(), min_size=5, max_size=5))
def test_the_switch_reads_the_usual_boolean_words_in_any_case(word, cases):
    value = "".join(c.upper() if upper else c for c, upper in zip(word, cases, strict=False))
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(kernels.SWITCH, value)
        assert kernels.enabled() is (word in SWITCH_ON)
        if word in SWITCH_OFF:
            assert kernels.kernel(NAME) is None


def test_the_switch_unset_is_on(monkeypatch):
    monkeypatch.delenv(kernels.SWITCH, raising=False)
    assert kernels.enabled() is True


ENV_TEXT = st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00"), max_size=12)


@given(value=ENV_TEXT.filter(lambda v: v.lower() not in SWITCH_ON + SWITCH_OFF))
def test_any_other_switch_value_is_refused_in_one_line_naming_it(value):
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(kernels.SWITCH, value)
        with pytest.raises(ConfigError) as refused:
            kernels.kernel(NAME)
    message = str(refused.value)
    assert message.startswith(f"NERFEXP_KERNELS={value!r}: expected on or off") and "\n" not in message


def test_a_run_with_another_switch_value_stops_before_its_directory_is_made(tmp_path, monkeypatch):
    monkeypatch.setenv(kernels.SWITCH, "disabled")
    run_dir = tmp_path / "run"
    result = run_nerfexp(*TINY, f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert result.returncode == 1
    assert result.stderr.strip().splitlines()[-1] == ("nerfexp: error: NERFEXP_KERNELS='disabled': expected on or "
                                                      "off (on, true, yes, 1, off, false, no, 0, in any case), or "
                                                      "unset (on)")
    assert not run_dir.exists()
