"""``trainer.precision=auto``: bf16 mixed precision where this machine computes bf16 matrix products in
hardware, float32 elsewhere, chosen when a job starts.

bf16 is fast on GPUs from Ampere on (compute capability 8.0) and on CPUs with AMX or AVX-512 BF16 units
(Intel from Cooper Lake and Sapphire Rapids, AMD from Zen 4): there ``bf16-mixed`` runs the networks' matrix
products in bf16 (weights, optimizer and volume rendering stay float32, ``nerfexp.nerf``). Elsewhere ``auto``
keeps ``32-true``, and so it does on a CPU where a component the run builds says that autocast slows its step
there (a class attribute ``CPU_AUTOCAST_SLOWER``, the measurement in words: the hash encoding's lookups stay
float32, so autocast only adds casts around its small field). docs/precision.md has the measurements behind the choice (``benchmarks/precision.py``,
and quality paired by seed).
"""

import logging
from pathlib import Path

import torch
from hydra.utils import get_class
from omegaconf import DictConfig, OmegaConf, open_dict

log = logging.getLogger(__name__)

AUTO = "auto"
CPU_BF16_FLAGS = ("amx_bf16", "avx512_bf16")  # /proc/cpuinfo's names of the CPU's bf16 matrix units
CPUINFO = Path("/proc/cpuinfo")


def cpu_bf16_units(cpuinfo: str) -> list[str]:
    """The bf16 units (``CPU_BF16_FLAGS``) that a Linux ``/proc/cpuinfo`` text lists among its first CPU's flags."""
    for line in cpuinfo.splitlines():
        if line.startswith("flags"):
            flags = set(line.partition(":")[2].split())
            return [flag for flag in CPU_BF16_FLAGS if flag in flags]
    return []


def fast_bf16(device_type: str) -> tuple[bool, str]:
    """Whether a ``device_type`` ("cpu" or "cuda") device here computes bf16 matrix products in hardware, and
    what says so, in words."""
    if device_type == "cuda":
        major, minor = torch.cuda.get_device_capability()
        name = torch.cuda.get_device_name()
        return major >= 8, f"{name}, compute capability {major}.{minor}"
    try:
        units = cpu_bf16_units(CPUINFO.read_text())
    except OSError:
        return False, "this CPU's bf16 units are unknown (no /proc/cpuinfo)"
    if units:
        return True, f"this CPU has {' and '.join(units)}"
    return False, "this CPU has no bf16 units (amx_bf16, avx512_bf16)"


def device_type(accelerator: str) -> str:
    """The device kind a trainer with ``accelerator`` runs on: "cuda" or "cpu" (``auto`` takes a GPU if any)."""
    if accelerator in ("gpu", "cuda") or (accelerator == AUTO and torch.cuda.is_available()):
        return "cuda"
    return "cpu"


def config_targets(node) -> list[str]:
    """Every ``_target_`` string in ``node`` (a plain dict, list or value, e.g. a resolved config), depth first."""
    if isinstance(node, dict):
        found = [node["_target_"]] if isinstance(node.get("_target_"), str) else []
        return found + [target for key, value in node.items() if key != "_target_" for target in config_targets(value)]
    if isinstance(node, list):
        return [target for value in node for target in config_targets(value)]
    return []


def cpu_autocast_slower(targets: list[str]) -> list[tuple[str, str]]:
    """(class name, measurement) of each class among ``targets`` that declares autocast slows its step on a CPU
    (``CPU_AUTOCAST_SLOWER``); targets that are not classes nerfexp can import are skipped."""
    slower = {}
    for target in targets:
        try:
            cls = get_class(target)
        except Exception:  # a function, or a target the settings check names: not this rule's to judge
            continue
        if isinstance(reason := getattr(cls, "CPU_AUTOCAST_SLOWER", None), str):
            slower[cls.__name__] = reason
    return list(slower.items())


def auto_precision(accelerator: str, targets: list[str] = ()) -> tuple[str, str]:
    """(``bf16-mixed`` or ``32-true``, why) for a trainer with ``accelerator`` on this machine building the
    components ``targets`` (``_target_`` strings): bf16 where the device computes it in hardware, unless on a
    CPU a component says autocast slows it there (``cpu_autocast_slower``)."""
    device = device_type(accelerator)
    fast, why = fast_bf16(device)
    slower = cpu_autocast_slower(list(targets)) if fast and device == "cpu" else []
    if slower:
        return "32-true", f"{why}, but " + "; ".join(f"{name}: {reason}" for name, reason in slower)
    return ("bf16-mixed" if fast else "32-true"), why


def model_targets(cfg: DictConfig) -> list[str]:
    """The ``_target_`` of every component the run's ``model`` builds, its interpolations followed."""
    return config_targets(OmegaConf.to_container(cfg.model, resolve=True)) if "model" in cfg else []


def fill_precision(cfg: DictConfig) -> None:
    """Set ``trainer.precision=auto`` in ``cfg`` to the precision this machine runs fast (``auto_precision``),
    in place and said in the log, so that the trainer built from ``cfg``, the checkpoints' settings and the
    config a run records hold the precision used. Any other value stays."""
    if cfg.trainer.get("precision") != AUTO:
        return
    precision, why = auto_precision(str(cfg.trainer.get("accelerator", AUTO)), model_targets(cfg))
    log.info("trainer.precision=auto: %s (%s)", precision, why)
    with open_dict(cfg.trainer):
        cfg.trainer.precision = precision
