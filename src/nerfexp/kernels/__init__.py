"""Fused CPU kernels (C++), built at first use with torch's own ``cpp_extension`` and cached (torch's extension
cache: ``TORCH_EXTENSIONS_DIR``, else ``~/.cache/torch_extensions``), so that an install needs no compiler and a
machine without one runs the pure torch path: ``kernel(name)`` is the built module, or None after one log line
saying why (no compiler, a failed build, ``NERFEXP_KERNELS=off``). Why C++ rather than numba or
``torch.compile``: ``benchmarks/kernel_tools.py`` (docs/acceleration.md).

Each kernel is compiled -O3 for the architecture's baseline (no -march=native: a cache shared between machines
must not hold instructions another CPU lacks), with OpenMP, as ATen's ``at::parallel_for`` uses it.
"""

import functools
import logging
import os
import time
from importlib.resources import files
from types import ModuleType

log = logging.getLogger(__name__)

SWITCH = "NERFEXP_KERNELS"  # "off": the torch path everywhere (the reference; tests compare the two)


def enabled() -> bool:
    """Whether kernels may be used at all (``NERFEXP_KERNELS`` is not "off")."""
    return os.environ.get(SWITCH, "on").lower() != "off"


@functools.cache
def _built(name: str) -> ModuleType | None:
    """The kernel ``name`` (``NAME.cpp`` beside this file) built, or None with one log line."""
    source = files(__name__) / f"{name}.cpp"
    started = time.perf_counter()
    try:
        from torch.utils.cpp_extension import load

        built = load(f"nerfexp_{name}", [str(source)], extra_cflags=["-O3", "-fopenmp"], extra_ldflags=["-fopenmp"],
                     verbose=False)
    except Exception as error:  # no compiler, no ninja, a failed build: the torch path runs instead
        reason = str(error).strip().splitlines()[-1] if str(error).strip() else type(error).__name__
        log.info("kernel %s not built (%s): the torch path runs instead (docs/acceleration.md)", name, reason)
        return None
    seconds = time.perf_counter() - started
    if seconds > 1:  # compiled now, not read from the cache: once per machine and source
        log.info("kernel %s built in %.0f s (cached for later runs)", name, seconds)
    return built


def kernel(name: str) -> ModuleType | None:
    """The built kernel ``name``, or None where kernels are off or it cannot be built (said once)."""
    return _built(name) if enabled() else None
