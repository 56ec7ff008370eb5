"""``trainer.precision=auto``: bf16 mixed precision where this machine computes bf16 matrix products in
hardware, float32 elsewhere, chosen when a job starts.

bf16 is fast on GPUs from Ampere on (compute capability 8.0) and on CPUs with AMX or AVX-512 BF16 units
(Intel from Cooper Lake and Sapphire Rapids, AMD from Zen 4): there ``bf16-mixed`` runs the networks' matrix
products in bf16 (weights, optimizer and volume rendering stay float32, ``nerfexp.nerf``). Elsewhere ``auto``
keeps ``32-true``. docs/precision.md has the measurements behind the choice (``benchmarks/precision.py``,
and quality paired by seed).
"""

import logging
from pathlib import Path

import torch
from omegaconf import DictConfig, open_dict

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


def auto_precision(accelerator: str) -> tuple[str, str]:
    """(``bf16-mixed`` or ``32-true``, why) for a trainer with ``accelerator`` on this machine."""
    fast, why = fast_bf16(device_type(accelerator))
    return ("bf16-mixed" if fast else "32-true"), why


def fill_precision(cfg: DictConfig) -> None:
    """Set ``trainer.precision=auto`` in ``cfg`` to the precision this machine runs fast (``auto_precision``),
    in place and said in the log, so that the trainer built from ``cfg``, the checkpoints' settings and the
    config a run records hold the precision used. Any other value stays."""
    if cfg.trainer.get("precision") != AUTO:
        return
    precision, why = auto_precision(str(cfg.trainer.get("accelerator", AUTO)))
    log.info("trainer.precision=auto: %s (%s)", precision, why)
    with open_dict(cfg.trainer):
        cfg.trainer.precision = precision
