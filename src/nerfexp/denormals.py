"""CPU denormals flushed to zero on every thread torch computes on, not only the one that asks.

``torch.set_flush_denormal`` sets the flush-to-zero and denormals-are-zero bits of the calling thread's floating-point
control register (x86's MXCSR). torch's intra-op work runs on an OpenMP team: the calling thread and workers that
the runtime started at the first parallel region and keeps. A worker started before the flag was set keeps IEEE
denormals, so with 2 threads half of every parallel operator kept computing on denormals, which grow as a run learns
its scene (what that cost: benchmarks/results/denormals.md).

``set_flush_denormal_everywhere`` runs ``torch.set_flush_denormal`` on each thread of the calling thread's OpenMP
team, through the runtime's own entry point for a parallel region (``GOMP_parallel``, which GNU's libgomp and LLVM's
libomp both export), found among the libraries this process has loaded: the runtime torch itself uses. Where there is
none (another parallel backend, a system without ``/proc/self/maps``), only the calling thread's flag is set, as torch
alone does, and the caller is told.
"""

import ctypes
import functools
import os
from pathlib import Path

import torch

OPENMP_LIBRARIES = ("libgomp", "libomp", "libiomp")  # GNU's, LLVM's, Intel's: each exports GOMP_parallel
PARALLEL_REGION = ctypes.CFUNCTYPE(None, ctypes.c_void_p)  # void (*fn)(void *data), run by each thread of the team


def flushes_denormals() -> bool:
    """Whether this thread's CPU arithmetic flushes float32 denormals to zero (torch sets it, but has no getter)."""
    return (torch.tensor(torch.finfo(torch.float32).tiny) / 2).item() == 0.0


@functools.cache
def openmp_runtime() -> ctypes.CDLL | None:
    """The OpenMP runtime this process has loaded (torch's), whose ``GOMP_parallel`` runs a function on each thread
    of a team; None where no loaded library is one (or has no such entry point), or the process's maps cannot be
    read (not Linux)."""
    try:
        maps = Path("/proc/self/maps").read_text().splitlines()
    except OSError:
        return None
    fields = (line.split(maxsplit=5) for line in maps)  # address, perms, offset, device, inode[, path]
    paths = dict.fromkeys(f[5] for f in fields if len(f) == 6)
    torch_libraries = str(Path(torch.__file__).parent)
    for path in sorted(paths, key=lambda path: not path.startswith(torch_libraries)):  # torch's own first
        if Path(path).name.startswith(OPENMP_LIBRARIES):
            try:
                runtime = ctypes.CDLL(path)  # already loaded: the same library, not a second copy
                runtime.GOMP_parallel.argtypes = [PARALLEL_REGION, ctypes.c_void_p, ctypes.c_uint, ctypes.c_uint]
                runtime.GOMP_parallel.restype = None
            except (OSError, AttributeError):
                continue
            return runtime
    return None


def set_flush_denormal_everywhere(on: bool) -> bool:
    """``torch.set_flush_denormal(on)`` on the calling thread and on each thread of its OpenMP team, which torch's
    parallel operators run on. Returns whether the team's threads were reached (False: the calling thread only,
    ``openmp_runtime`` found none).

    The team is made as large as torch's thread count or the CPUs, whichever is more: the runtime keeps the threads
    of a team that shrank and takes them back when it grows (``ThreadsFollowLoad`` moves the count while a run
    trains), so each must hold the flag; a thread it starts later copies the flag of the thread that starts it, as a
    new thread copies its creator's floating-point environment."""
    torch.set_flush_denormal(on)
    runtime = openmp_runtime()
    if runtime is None:
        return False
    region = PARALLEL_REGION(lambda data: torch.set_flush_denormal(on))  # each thread takes the GIL to run it
    team = max(torch.get_num_threads(), os.cpu_count() or 1)
    runtime.GOMP_parallel(region, None, team, 0)  # CDLL calls release the GIL meanwhile
    return True
