"""Fused CPU kernels (C++), built at first use with torch's own ``cpp_extension`` and cached in torch's extension
cache (``TORCH_EXTENSIONS_DIR``, else ``~/.cache/torch_extensions``), so that an install needs no compiler and a
machine without one runs the pure torch path: ``kernel(name)`` is the built module, or None after one log line
saying why (no compiler, a failed build, a cache others can write, ``NERFEXP_KERNELS=off``). A cached build is
imported only where it is the one nerfexp built here (``nerfexp.kernels.cache``: a record beside it, checked
first); anything else is rebuilt. Why C++ rather than numba or ``torch.compile``: ``benchmarks/kernel_tools.py``
(docs/acceleration.md).

A build takes about a minute, once per machine and source: it is no part of a run's training time. A run builds
(or reads from the cache) the kernels its components will use before its training clock starts (``prepare``,
called by ``nerfexp.training.recorders.RunRecorder``), and ``seconds_spent`` says how long this process spent
getting kernels, so that a kernel first asked for inside the clock is taken out of it all the same.

Each kernel is compiled -O3 with OpenMP, as ATen's ``at::parallel_for`` uses it, and on x86-64 for this CPU's vector
instructions without fused multiply-adds (``nerfexp.kernels.cache.NATIVE``: the baseline build's results, bit for bit).
"""

import functools
import logging
import os
import time
from importlib.resources import files
from types import ModuleType

from nerfexp.errors import ConfigError
from nerfexp.kernels.cache import NotBuilt, cached_kernel

log = logging.getLogger(__name__)

SWITCH = "NERFEXP_KERNELS"  # off: the torch path everywhere (the reference; tests compare the two)
SWITCH_WORDS = {"on": True, "true": True, "yes": True, "1": True, "off": False, "false": False, "no": False,
                "0": False}  # any case


def enabled() -> bool:
    """Whether kernels may be used at all: ``NERFEXP_KERNELS`` read as a boolean word (``SWITCH_WORDS``, any
    case; unset: on). Any other value is a ConfigError naming the variable and the value, never a guess."""
    value = os.environ.get(SWITCH)
    if value is None:
        return True
    if value.lower() not in SWITCH_WORDS:
        raise ConfigError(f"{SWITCH}={value!r}: expected on or off ({', '.join(SWITCH_WORDS)}, in any case), "
                          f"or unset (on)")
    return SWITCH_WORDS[value.lower()]


_SPENT: dict[str, float] = {}  # kernel name -> seconds its first use in this process took (built or read)


def seconds_spent() -> float:
    """Seconds this process has spent getting kernels (building them, or reading them from the cache), so far."""
    return sum(_SPENT.values())


@functools.cache
def _built(name: str) -> ModuleType | None:
    """The kernel ``name`` (``NAME.cpp`` beside this file), or None with one log line; a build made now is said
    in one line too (with why, where a cached one failed its check)."""
    started = time.perf_counter()
    try:
        built, now, failed = cached_kernel(name, (files(__name__) / f"{name}.cpp").read_bytes())
    except NotBuilt as error:  # no compiler, no ninja, a failed build, a cache others can write
        log.info("kernel %s not built (%s): the torch path runs instead (docs/acceleration.md)", name, error)
        return None
    finally:
        _SPENT[name] = time.perf_counter() - started
    seconds = _SPENT[name]
    if now and failed is None:  # compiled now, not read from the cache: once per machine and source
        log.info("kernel %s built in %.0f s (cached for later runs)", name, seconds)
    elif now:
        log.info("kernel %s rebuilt in %.0f s (cached for later runs): its cached build failed a check: %s", name,
                 seconds, failed)
    return built


def kernel(name: str) -> ModuleType | None:
    """The built kernel ``name``, or None where kernels are off or it cannot be built (said once)."""
    return _built(name) if enabled() else None


def prepare(names: list[str]) -> float:
    """Each kernel of ``names`` built or read from the cache now (``kernel``), once; the seconds it took."""
    before = seconds_spent()
    for name in dict.fromkeys(names):
        kernel(name)
    return seconds_spent() - before
