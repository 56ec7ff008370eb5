"""``trainer.precision=auto``: bf16 mixed precision where this machine computes bf16 matrix products in
hardware and, on a CPU, a step of the run's own field is measured faster in bf16; float32 elsewhere; chosen when a
job starts.

bf16 is fast on GPUs from Ampere on (compute capability 8.0) and on CPUs with AMX or AVX-512 BF16 units
(Intel from Cooper Lake and Sapphire Rapids, AMD from Zen 4): there ``bf16-mixed`` runs the networks' matrix
products in bf16 (weights, optimizer and volume rendering stay float32, ``nerfexp.nerf``). Elsewhere ``auto``
keeps ``32-true``, and so it does on a CPU where a component the run builds says that autocast slows its step
there (a class attribute ``CPU_AUTOCAST_SLOWER``, the measurement in words: the hash encoding's lookups stay
float32, so autocast only adds casts around its small field). Otherwise, on a CPU, units are not speed: the same
AVX-512 BF16 units made bf16 faster on one CPU and slower on another (docs/precision.md, measured, not assumed).
So there ``auto`` times the run's colour field, forward and backward over a step's points, in both
precisions (``measured_precision``) and takes bf16 only where it is at least ``MEASURED_MARGIN`` times faster; the
answer is kept per machine, threads and field (``precision_cache``), so that a sweep's jobs and a resumed run
choose alike. docs/precision.md has the measurements behind the choice (``benchmarks/kernels/precision.py``, and quality
paired by seed).
"""

import hashlib
import json
import logging
import os
import time
from pathlib import Path

import torch
from hydra.utils import get_class, instantiate
from omegaconf import DictConfig, OmegaConf, open_dict

from nerfexp.files import atomic_write

log = logging.getLogger(__name__)

AUTO = "auto"
CPU_BF16_FLAGS = ("amx_bf16", "avx512_bf16")  # /proc/cpuinfo's names of the CPU's bf16 matrix units
CPUINFO = Path("/proc/cpuinfo")
MEASURED_MARGIN = 1.1  # bf16 chosen on a CPU only where a field's step is at least this many times faster in it
MEASURED_POINTS = 32_768  # at most this many points in the measured step (the default's step: 256 rays x 96)
MEASURED_REPEATS = 5  # timed steps in each precision, alternating, after one warm-up each; the fastest compared
CACHE_VARIABLE = "NERFEXP_PRECISION_CACHE"  # where auto keeps its measurements (``precision_cache``)


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


def precision_cache() -> Path:
    """The folder of auto's measurements: ``NERFEXP_PRECISION_CACHE``, else ``$XDG_CACHE_HOME/nerfexp/precision``
    (``~/.cache/nerfexp/precision``)."""
    if os.environ.get(CACHE_VARIABLE):
        return Path(os.environ[CACHE_VARIABLE])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "nerfexp" / "precision"


def field_step_s(field: torch.nn.Module, inputs: tuple[torch.Tensor, ...], bf16: bool) -> float:
    """Seconds of one forward and backward pass of ``field`` at ``inputs`` (points [N, 3], directions [N, 3] and,
    where it takes them, appearance codes [N, D]), under CPU bf16 autocast where ``bf16``."""
    started = time.perf_counter()
    with torch.autocast("cpu", torch.bfloat16, enabled=bf16):
        outputs = field(*inputs)
    (outputs.rgb.float().sum() + outputs.sigma.float().sum()).backward()
    return time.perf_counter() - started


def measure_field(cfg: DictConfig) -> tuple[float, float, int]:
    """The seconds of a step of the run's colour field (``model.renderer.field``, built as the renderer builds it) in
    float32 and in bf16 autocast, each the fastest of ``MEASURED_REPEATS`` (the step least disturbed by other
    work), alternating after a warm-up step each, and its points: a step's
    samples (``datamodule.batch_rays`` x the sampler's samples per ray, all networks), at most ``MEASURED_POINTS``.
    Draws on forked random numbers: the run's own stay as they were."""
    renderer = cfg.model.renderer
    appearance = renderer.get("appearance")
    dim = int(appearance.dim) if appearance is not None else 0
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        samples = instantiate(renderer.sampler)().samples_per_ray
        field = instantiate(renderer.field)(**({"appearance_dim": dim} if dim else {}))
        n = min(int(cfg.datamodule.batch_rays) * samples, MEASURED_POINTS)
        directions = torch.nn.functional.normalize(torch.randn(n, 3), dim=-1)
        inputs = (torch.rand(n, 3) * 2 - 1, directions, *((torch.zeros(n, dim),) if dim else ()))
        seconds = {False: [], True: []}
        for bf16 in (False, True):  # warm-up: oneDNN builds its kernels for a new shape at its first call
            field_step_s(field, inputs, bf16)
        for _ in range(MEASURED_REPEATS):
            for bf16 in (False, True):
                seconds[bf16].append(field_step_s(field, inputs, bf16))
    return min(seconds[False]), min(seconds[True]), n


def measured_key(cfg: DictConfig) -> str:
    """What a measurement of ``measure_field`` depends on, hashed: the CPU (its model and flags), torch, the
    threads, and the field, sampler, appearance and batch the run builds."""
    try:
        cpu = CPUINFO.read_text().split("\n\n")[0]
    except OSError:
        cpu = "unknown"
    renderer = OmegaConf.to_container(cfg.model.renderer, resolve=True)
    what = {"cpu": cpu, "torch": torch.__version__, "threads": torch.get_num_threads(),
            "batch_rays": cfg.datamodule.batch_rays,
            **{key: renderer.get(key) for key in ("field", "sampler", "appearance")}}
    return hashlib.sha256(json.dumps(what, sort_keys=True, default=str).encode()).hexdigest()[:32]


def measured_precision(cfg: DictConfig, why: str) -> tuple[str, str]:
    """(``bf16-mixed`` or ``32-true``, why) on a CPU with bf16 units (``why`` says which): bf16 where the run's
    colour field's step was measured at least ``MEASURED_MARGIN`` times faster in it (``measure_field``). The
    measurement is kept in ``precision_cache()`` under ``measured_key`` and read back (as data: a file that does not
    hold one is measured again), so that runs of one config on one machine choose alike; where it cannot be kept (a
    cache folder that cannot be made or written), the words say so, naming the record's file."""
    cache = precision_cache() / f"{measured_key(cfg)}.json"
    try:
        record = json.loads(cache.read_text())
        float32_s, bf16_s, points = float(record["float32_s"]), float(record["bf16_s"]), int(record["points"])
        source = f"measured before, {cache}"
    except (OSError, ValueError, KeyError, TypeError):
        try:
            float32_s, bf16_s, points = measure_field(cfg)
        except Exception as error:  # a field that needs the scene to be built: the model's build will say more
            return "bf16-mixed", f"{why} (this run's field not measured: {type(error).__name__}: {error})"
        source = "measured now"
        try:
            cache.parent.mkdir(parents=True, exist_ok=True)
            # whole or not at all: the jobs of a joblib sweep may write one record at once
            atomic_write(cache, json.dumps({"float32_s": float32_s, "bf16_s": bf16_s, "points": points}).encode())
        except OSError as error:  # a cache that cannot be written: this run's choice stands, said; the next measures
            source = f"measured now, not kept: {cache} cannot be written ({error.strerror or error})"
    faster = float32_s >= MEASURED_MARGIN * bf16_s
    words = (f"{why}; a step of this run's field, {points:,} points, took {bf16_s:.4f} s in bf16 against "
             f"{float32_s:.4f} s in float32 here ({source}; bf16 where it is at least {MEASURED_MARGIN}x faster)")
    return ("bf16-mixed" if faster else "32-true"), words


def fill_precision(cfg: DictConfig) -> None:
    """Set ``trainer.precision=auto`` in ``cfg`` to the precision this machine runs fast (``auto_precision``,
    then on a CPU with bf16 units ``measured_precision``), in place and said in the log, so that the trainer built
    from ``cfg``, the checkpoints' settings and the config a run records hold the precision used. Any other value
    stays."""
    if cfg.trainer.get("precision") != AUTO:
        return
    accelerator = str(cfg.trainer.get("accelerator", AUTO))
    precision, why = auto_precision(accelerator, model_targets(cfg))
    if precision == "bf16-mixed" and device_type(accelerator) == "cpu" and "model" in cfg:
        precision, why = measured_precision(cfg, why)
    log.info("trainer.precision=auto: %s (%s)", precision, why)
    with open_dict(cfg.trainer):
        cfg.trainer.precision = precision
