"""Fused CPU kernels (C++), built at first use with torch's own ``cpp_extension`` and cached in torch's extension
cache (``TORCH_EXTENSIONS_DIR``, else ``~/.cache/torch_extensions``), so that an install needs no compiler and a
machine without one runs the pure torch path: ``kernel(name)`` is the built module, or None where
``NERFEXP_KERNELS=off`` or after one log line saying why (no compiler, a failed build, a cache others can write). A
cached build is imported only where it is the one nerfexp built here (``nerfexp.kernels.cache``: a record beside
it, checked first); anything else is rebuilt. Why C++ rather than numba or ``torch.compile``:
``benchmarks/kernels/kernel_tools.py`` (docs/acceleration.md).

A build takes about a minute, once per machine and source: it is no part of a run's training time. A run builds
(or reads from the cache) the kernels its components will use before its training clock starts (``prepare``,
called by ``nerfexp.training.recorders.RunRecorder``, which says in one line what each came to: built, loaded
from the cache, not built and why, or off), and ``seconds_spent`` says how long this process spent getting
kernels, so that a kernel first asked for inside the clock is taken out of it all the same. A build, and a wait for
another process's build, are said as they start (``nerfexp.kernels.cache``).

Each kernel is compiled -O3 with OpenMP, as ATen's ``at::parallel_for`` uses it, and on x86-64 for this CPU's vector
instructions without fused multiply-adds (``nerfexp.kernels.cache.NATIVE``: the baseline build's results, bit for bit).
"""

import functools
import logging
import os
import time
from importlib.resources import files
from types import ModuleType
from typing import NamedTuple

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
_SAID: set[str] = set()  # the kernels whose outcome this process has said (``kernel``, ``prepare``)


def seconds_spent() -> float:
    """Seconds this process has spent getting kernels (building them, or reading them from the cache), so far."""
    return sum(_SPENT.values())


class Outcome(NamedTuple):
    """What getting a kernel came to: the ``module`` (None: the torch path runs), what happened in words
    (``text``: "built in 62 s (cached for later runs)", "loaded from the cache", "not built (why): ..."), and
    whether it is worth a line of its own where it happens (``news``: a build, a rebuild, a failure; a load from
    the cache is not)."""

    module: ModuleType | None
    text: str
    news: bool


@functools.cache
def _built(name: str) -> Outcome:
    """The kernel ``name`` (``NAME.cpp`` beside this file) built or read from the cache, once per process, and what
    that came to (with why, where a cached build failed its check or none could be had)."""
    started = time.perf_counter()
    try:
        built, now, failed = cached_kernel(name, (files(__name__) / f"{name}.cpp").read_bytes())
    except NotBuilt as error:  # no compiler, no ninja, a failed build, a cache others can write
        return Outcome(None, f"not built ({error}): the torch path runs instead (docs/acceleration.md)", True)
    finally:
        _SPENT[name] = time.perf_counter() - started
    seconds = _SPENT[name]
    if now and failed is None:  # compiled now, not read from the cache: once per machine and source
        return Outcome(built, f"built in {seconds:.0f} s (cached for later runs)", True)
    if now:
        return Outcome(built, f"rebuilt in {seconds:.0f} s (cached for later runs): its cached build failed a "
                              f"check: {failed}", True)
    return Outcome(built, "loaded from the cache", False)


def kernel(name: str) -> ModuleType | None:
    """The built kernel ``name``, or None where kernels are off or it cannot be built; a build, or why there is
    none, said in one line the first time (unless ``prepare`` said it)."""
    if not enabled():
        return None
    outcome = _built(name)
    if outcome.news and name not in _SAID:
        _SAID.add(name)
        log.info("kernel %s %s", name, outcome.text)
    return outcome.module


def prepare(names: list[str]) -> dict[str, str]:
    """Each kernel of ``names`` built, read from the cache, or left off (``NERFEXP_KERNELS``) now, once:
    ``{name: what happened, in words}`` (``Outcome.text``; "(got earlier in this process)" after one this process
    had already got), for the caller to say in one line."""
    if not enabled():
        off = f"off ({SWITCH}={os.environ[SWITCH]}): the torch path runs instead"
        return {name: off for name in dict.fromkeys(names)}
    said = {}
    for name in dict.fromkeys(names):
        earlier = name in _SPENT
        outcome = _built(name)
        _SAID.add(name)
        said[name] = f"{outcome.text} (got earlier in this process)" if earlier else outcome.text
    return said


def prepared_line(outcomes: dict[str, str]) -> str:
    """One line of what ``prepare`` came to, kernel by kernel.

    >>> prepared_line({"hash_encoding": "loaded from the cache", "lazy_adam": "built in 61 s"})
    'kernels, before the training clock started: hash_encoding loaded from the cache; lazy_adam built in 61 s'
    """
    return "kernels, before the training clock started: " + "; ".join(
        f"{name} {text}" for name, text in outcomes.items())
