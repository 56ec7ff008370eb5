"""Precision as a measured axis: each component's training step in float32 and under bfloat16 autocast.
Writes benchmarks/results/precision.{json,md}.

bf16 here is what Lightning's ``bf16-mixed`` (``trainer=bf16``) does: the step's forward runs under
``torch.autocast(device, dtype=torch.bfloat16)``, weights, gradients and the optimizer stay float32.
A step is forward + backward + Adam step on fixed random inputs (the optimizer and its parameter groups
as ``NeRFModule`` builds them). Seconds per step: the median of ``--repeats`` samples after ``--warmup``
steps, float32 and bf16 alternating so that both see the same machine; a sample is the mean of as many
consecutive steps as last ``MIN_SAMPLE_S`` (one, except for the grid's). Components are built from the
real config (``nerfexp.conf``: ``scale=cpu`` and ``scale=paper``, with ``encoding=hashgrid``, ``view_dependence=sh``,
``acceleration=occupancy`` where named), so their sizes are those of a training run:
- ``field``: the positional-encoding field (gamma(x) L = 10, the trunk, ``MLPViewDependence``);
- ``hashgrid_field``: ``HashGridEncoding`` and its one-layer field; ``hashgrid_encoding``: the encoding alone;
- ``sh_field``: the field with ``SphericalHarmonicsViewDependence``;
- ``occupancy_update``: ``OccupancyGrid.update`` over all cells (the warm-up) with the field's density,
  no gradient; ``occupied_at``: the grid's lookup of a batch of samples;
- ``renderer``: ``VolumeRenderer``, coarse and fine networks, the losses of both, as ``NeRFModule`` trains.
Before timing, each component's outputs in bf16 are compared with float32's on the same weights and inputs
(``max_rel_diff``: the largest |bf16 - fp32| / |fp32|, elements below a thousandth of the largest
|fp32| measured against that thousandth); a component whose bf16 output is not within ``CLOSE`` of
float32's is timed but marked, as its speed would be no result. Where bf16 is slower, one profiled step of
each (``torch.profiler``) names the operators whose time grew most.

Runs on the CPU, and on the GPU too where ``torch.cuda.is_available()``.

    python benchmarks/kernels/precision.py [--repeats 21] [--warmup 2] [--threads N] [--only NAME ...]
"""

import argparse
import copy
import json
import math
import os
import platform
import statistics
import subprocess
import time
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from hydra import compose, initialize_config_module
from hydra.utils import instantiate
from omegaconf import DictConfig
from torch import Tensor, nn
from torch.profiler import ProfilerActivity, profile

from nerfexp.files import atomic_write
from nerfexp.nerf.bounds import Bounded
from nerfexp.rundir import layout
from nerfexp.training.module import NeRFModule

RESULTS = Path(__file__).parents[1] / "results"  # benchmarks/results
BOX = [[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]]  # the hash grid's and the occupancy grid's box, around the built-in scene
CLOSE = 0.02  # the largest relative difference of bf16's outputs from float32's that counts as the same output
# (bf16 rounds to 2^-8 = 0.4 %: this is a few roundings, far below what a wrong kernel would give)
MIN_SAMPLE_S = 0.1  # a timed sample lasts at least this: steps shorter than it are timed in runs
PROFILE_STEPS = 5  # steps profiled in each precision where bf16 is slower
CPU_FLAGS = ("avx512f", "avx512_bf16", "amx_tile", "amx_bf16")
PAPER_FIELD_POINTS = 16_384  # 1/48 of the paper's fine batch (4,096 rays x 192 samples): about a second on 2 cores
PAPER_RENDER_RAYS = 256  # the paper's complete model on 256 rays (1/16 of its batch): 256 x (64 + 192) evaluations


@dataclass
class Workload:
    """A component on a device: ``forward(deterministic)`` -> named outputs (``deterministic``: the
    renderer's samples without jitter; the others ignore it); ``optimizer`` None where the component has
    nothing to train (the grid's update and lookup: the step is the forward)."""

    forward: Callable[[bool], dict[str, Tensor]]
    optimizer: torch.optim.Optimizer | None
    targets: dict[str, Tensor]


@dataclass
class Component:
    name: str
    scale: str
    batch: str  # the inputs of one step, in words
    overrides: tuple[str, ...]
    build: Callable[[DictConfig, torch.device], Callable[[], Workload]]  # -> a maker of identical workloads


def config(scale: str, overrides: tuple[str, ...]) -> DictConfig:
    with initialize_config_module("nerfexp.conf", version_base=None):
        return compose("config", overrides=[f"scale={scale}", *overrides])


def bounded(module: nn.Module) -> nn.Module:
    """``module`` with every box-bound part (hash grid, occupancy grid) given ``BOX``."""
    for part in module.modules():
        if isinstance(part, Bounded):
            part.set_bounds(torch.tensor(BOX))
    return module


def optimizer_for(cfg: DictConfig, module: nn.Module) -> torch.optim.Optimizer:
    """The run's optimizer over ``module``, with ``NeRFModule``'s parameter groups (tables without weight decay)."""
    return instantiate(cfg.model.optimizer)(NeRFModule.parameter_groups(module))


def random_points(n: int, device: torch.device, generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """n positions [n, 3] in ``BOX`` and unit directions [n, 3]."""
    low, high = torch.tensor(BOX)
    positions = low + (high - low) * torch.rand(n, 3, generator=generator)
    directions = F.normalize(torch.randn(n, 3, generator=generator), dim=-1)
    return positions.to(device), directions.to(device)


def random_rays(n: int, device: torch.device, generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """n rays (origins [n, 3] at radius 4, unit directions [n, 3]) through the middle of the scene."""
    origins = 4 * F.normalize(torch.randn(n, 3, generator=generator), dim=-1)
    aims = 0.5 * torch.randn(n, 3, generator=generator)
    return origins.to(device), F.normalize(aims - origins, dim=-1).to(device)


def field_workloads(points: int, encoding_only: bool = False):
    """A builder of field workloads: the config's field at ``points`` random samples (rgb and sigma; the
    position encoding's features alone with ``encoding_only``)."""

    def build(cfg: DictConfig, device: torch.device) -> Callable[[], Workload]:
        generator = torch.Generator().manual_seed(0)
        positions, directions = random_points(points, device, generator)
        field = bounded(instantiate(cfg.model.renderer.field)()).to(device).train()
        if encoding_only:
            targets = {"features": torch.rand(points, field.position_encoding.out_dim, generator=generator)}
        else:
            targets = {"rgb": torch.rand(points, 3, generator=generator),
                       "sigma": torch.rand(points, generator=generator)}
        targets = {name: target.to(device) for name, target in targets.items()}

        def make() -> Workload:
            net = copy.deepcopy(field)
            if encoding_only:
                encoding = net.position_encoding
                optimizer = instantiate(cfg.model.optimizer)(encoding.parameters(), weight_decay=0.0)  # tables
                return Workload(lambda _: {"features": encoding(positions)}, optimizer, targets)

            def forward(deterministic: bool) -> dict[str, Tensor]:
                out = net(positions, directions)
                return {"rgb": out.rgb, "sigma": out.sigma}
            return Workload(forward, optimizer_for(cfg, net), targets)
        return make
    return build


def occupancy_workloads(lookup: bool):
    """A builder of the occupancy grid's update over all its cells with the config's field's density, or
    (``lookup``) of ``occupied_at`` at a training batch of samples."""

    def build(cfg: DictConfig, device: torch.device) -> Callable[[], Workload]:
        field = instantiate(cfg.model.renderer.field)().to(device).train()
        grid = bounded(instantiate(cfg.acceleration.grid)).to(device)
        samples = cfg.scale.batch_rays * cfg.scale.n_single
        positions, _ = random_points(samples, device, torch.Generator().manual_seed(0))

        def make() -> Workload:
            if lookup:
                return Workload(lambda _: {"occupied": grid.occupied_at(positions)}, None, {})

            def update(deterministic: bool) -> dict[str, Tensor]:
                torch.manual_seed(0)  # the same jitter in both precisions
                grid.update(0, [field.density])
                return {"density": grid.density.clone()}
            return Workload(update, None, {})
        return make
    return build


def renderer_workloads(rays: int | None = None):
    """A builder of the config's model: ``VolumeRenderer`` on ``rays`` random rays (the scale's batch when
    None), the losses of every network against random colours, as ``NeRFModule.training_step``."""

    def build(cfg: DictConfig, device: torch.device) -> Callable[[], Workload]:
        n_rays = rays or cfg.scale.batch_rays
        generator = torch.Generator().manual_seed(0)
        origins, directions = random_rays(n_rays, device, generator)
        target = torch.rand(n_rays, 3, generator=generator).to(device)
        model = bounded(instantiate(cfg.model)).to(device).train()

        def make() -> Workload:
            module = copy.deepcopy(model)

            def forward(deterministic: bool) -> dict[str, Tensor]:
                outputs = module.renderer(origins, directions, deterministic=deterministic)
                return {name: out["rgb"] for name, out in outputs.items()}
            return Workload(forward, module.optimizer(module.parameter_groups()),
                            {name: target for name in ("coarse", "fine")})
        return make
    return build


def components() -> list[Component]:
    cpu_points = "24,576 points (scale=cpu: 256 rays x 96 samples)"
    return [
        Component("field", "cpu", cpu_points, (), field_workloads(256 * 96)),
        Component("field", "paper", f"{PAPER_FIELD_POINTS:,} points (1/48 of 4,096 rays x 192 samples)", (),
                  field_workloads(PAPER_FIELD_POINTS)),
        Component("hashgrid_field", "cpu", cpu_points, ("encoding=hashgrid",), field_workloads(256 * 96)),
        Component("hashgrid_encoding", "cpu", cpu_points, ("encoding=hashgrid",),
                  field_workloads(256 * 96, encoding_only=True)),
        Component("hashgrid_field", "paper", "24,576 points (as scale=cpu's batch)", ("encoding=hashgrid",),
                  field_workloads(256 * 96)),
        Component("sh_field", "cpu", cpu_points, ("view_dependence=sh",), field_workloads(256 * 96)),
        Component("occupancy_update", "cpu", "32,768 cells (32^3, every cell: the warm-up)",
                  ("acceleration=occupancy",), occupancy_workloads(lookup=False)),
        Component("occupied_at", "cpu", cpu_points, ("acceleration=occupancy",), occupancy_workloads(lookup=True)),
        Component("renderer", "cpu", "256 rays x (24 + 72) samples: one scale=cpu batch", (), renderer_workloads()),
        Component("renderer", "paper", f"{PAPER_RENDER_RAYS} rays x (64 + 192) samples (1/16 of the paper's batch)",
                  (), renderer_workloads(PAPER_RENDER_RAYS)),
    ]


def precision(bf16: bool, device: torch.device):
    return torch.autocast(device.type, dtype=torch.bfloat16) if bf16 else nullcontext()


def step(work: Workload, bf16: bool, device: torch.device) -> dict[str, Tensor]:
    """One training step (forward only where there is nothing to train); returns the outputs."""
    with precision(bf16, device):
        outputs = work.forward(False)
        if work.optimizer is None:
            return outputs
        loss = sum(F.mse_loss(outputs[k].float(), work.targets[k]) for k in work.targets)
    work.optimizer.zero_grad(set_to_none=True)
    loss.backward()
    work.optimizer.step()
    return outputs


def max_rel_diff(reference: Tensor, other: Tensor) -> float:
    """max |other - reference| / |reference|, each |reference| clamped below at 1e-3 of the largest."""
    reference, other = reference.double(), other.double()
    scale = reference.abs().clamp_min(1e-3 * float(reference.abs().max().clamp_min(torch.finfo(torch.float64).tiny)))
    return float(((other - reference).abs() / scale).max())


def agreement(make: Callable[[], Workload], device: torch.device) -> dict[str, float]:
    """Each output's ``max_rel_diff`` of bf16 from float32 (same weights and inputs, deterministic rays);
    for a boolean output, the fraction of elements that differ."""
    results = {}
    for bf16 in (False, True):
        with torch.no_grad(), precision(bf16, device):
            results[bf16] = make().forward(True)
    return {name: (float((results[True][name] != out).float().mean()) if out.dtype == torch.bool
                   else max_rel_diff(out, results[True][name]))
            for name, out in results[False].items()}


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def seconds(work: Workload, bf16: bool, device: torch.device, steps: int) -> float:
    """Mean seconds of ``steps`` consecutive steps."""
    synchronize(device)
    start = time.perf_counter()
    for _ in range(steps):
        step(work, bf16, device)
    synchronize(device)
    return (time.perf_counter() - start) / steps


def time_steps(make: Callable[[], Workload], device: torch.device, warmup: int,
               repeats: int) -> tuple[dict[bool, list[float]], int]:
    """Seconds per step in each precision, ``repeats`` times after ``warmup`` steps of each, alternating;
    each time the mean of enough consecutive steps to last ``MIN_SAMPLE_S`` (returned: the steps per time)."""
    works = {bf16: make() for bf16 in (False, True)}
    for _ in range(warmup):
        for bf16, work in works.items():
            step(work, bf16, device)
    steps = max(1, math.ceil(MIN_SAMPLE_S / seconds(works[False], False, device, 1)))
    times = {False: [], True: []}
    for _ in range(repeats):
        for bf16, work in works.items():
            times[bf16].append(seconds(work, bf16, device, steps))
    return times, steps


def grown_ops(make: Callable[[], Workload], device: torch.device, top: int = 6) -> list[dict]:
    """The operators whose self time per step grew most from float32 to bf16 (``PROFILE_STEPS`` profiled
    steps of each after two warm-up steps): [{op, fp32_ms, bf16_ms}], milliseconds per step."""
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    attribute = "self_device_time_total" if device.type == "cuda" else "self_cpu_time_total"
    per_op = {}
    for bf16 in (False, True):
        work = make()
        for _ in range(2):
            step(work, bf16, device)
        with profile(activities=activities) as prof:
            for _ in range(PROFILE_STEPS):
                step(work, bf16, device)
            synchronize(device)
        for event in prof.key_averages():
            ms = getattr(event, attribute) / 1e3 / PROFILE_STEPS
            per_op.setdefault(event.key, {False: 0.0, True: 0.0})[bf16] += ms
    grown = sorted(per_op.items(), key=lambda item: item[1][False] - item[1][True])[:top]
    return [{"op": op, "fp32_ms": round(ms[False], 2), "bf16_ms": round(ms[True], 2)}
            for op, ms in grown if ms[True] > ms[False]]


def cpu_model() -> str:
    """The CPU's model name and its timing units (``nerfexp.rundir.layout.cpu_model``)."""
    if not Path("/proc/cpuinfo").exists():
        return platform.processor() or platform.machine()
    return layout.cpu_model(Path("/proc/cpuinfo").read_text())


def cpu_flags() -> dict[str, bool]:
    """Which bf16-relevant instruction sets /proc/cpuinfo lists."""
    text = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    present = {flag for line in text.splitlines() if line.startswith("flags") for flag in line.split(":", 1)[1].split()}
    return {flag: flag in present for flag in CPU_FLAGS}


def source() -> dict:
    """The commit measured and the library and config files that differed from it (uncommitted work
    changes what is measured)."""
    def git(*args: str) -> str:
        run = subprocess.run(["git", *args], cwd=Path(__file__).parent, capture_output=True, text=True)
        return run.stdout if run.returncode == 0 else ""
    status = git("status", "--porcelain", "--untracked-files=all", "--", ":/src", ":/conf", ":/pyproject.toml")
    return {"commit": git("rev-parse", "--short", "HEAD").strip() or "unknown",
            "modified": [line[3:] for line in status.splitlines()]}


def machine_info() -> dict:
    info = {"cpu": cpu_model(), "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
            "cpu_flags": cpu_flags(), "torch": torch.__version__,
            "mkldnn_available": torch.backends.mkldnn.is_available(),
            "mkldnn_bf16_supported": bool(torch.ops.mkldnn._is_mkldnn_bf16_supported()),
            "cpu_capability": torch.backends.cpu.get_cpu_capability()}
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name()
    return info


def measure(component: Component, device: torch.device, warmup: int, repeats: int) -> dict:
    cfg = config(component.scale, component.overrides)
    torch.manual_seed(0)
    make = component.build(cfg, device)
    diffs = agreement(make, device)
    close = all(value <= CLOSE for value in diffs.values())
    times, steps = time_steps(make, device, warmup, repeats)
    fp32, bf16 = statistics.median(times[False]), statistics.median(times[True])
    paired = [f / b for f, b in zip(times[False], times[True], strict=True)]  # samples taken side by side
    quartiles = statistics.quantiles(paired, n=4) if len(paired) > 1 else [paired[0]] * 3
    row = {"component": component.name, "scale": component.scale, "device": device.type, "batch": component.batch,
           "fp32_s": float(f"{fp32:.4g}"), "bf16_s": float(f"{bf16:.4g}"), "fp32_over_bf16": round(fp32 / bf16, 3),
           "bf16_at_least_as_fast": bf16 <= fp32, "paired_ratio_quartiles": [round(q, 3) for q in quartiles],
           "max_rel_diff": {k: float(f"{v:.3g}") for k, v in diffs.items()},
           "close": close, "steps_per_sample": steps, "fp32_times_s": [float(f"{t:.4g}") for t in times[False]],
           "bf16_times_s": [float(f"{t:.4g}") for t in times[True]]}
    if bf16 > fp32:
        row["grown_ops"] = grown_ops(make, device)
    print(f"{device.type} {component.name} ({component.scale}): fp32 {fp32:.4f} s, bf16 {bf16:.4f} s, "
          f"ratio {fp32 / bf16:.2f}, max rel diff {row['max_rel_diff']}", flush=True)
    return row


def as_fast(row: dict) -> str:
    """yes, no, or no within noise: slower by the medians, but in at least a quarter of the side-by-side
    samples faster."""
    if row["bf16_at_least_as_fast"]:
        return "yes"
    return "no, within noise" if row["paired_ratio_quartiles"][2] >= 1 else "no"


def markdown(rows: list[dict], machine: dict, code: dict, args: argparse.Namespace, command: str) -> str:
    flags = ", ".join(f"{flag} {'yes' if present else 'no'}" for flag, present in machine["cpu_flags"].items())
    lines = ["# Precision: float32 against bf16 autocast, per component", "",
             f"Command: `{command}`. Seconds per step: the median of {args.repeats} timed samples after "
             f"{args.warmup} warm-up steps, float32 and bf16 alternating; a sample is the mean of enough "
             f"consecutive steps to last {MIN_SAMPLE_S} s (1 for most components). Code: {code['commit']}"
             + (f" with uncommitted changes to {', '.join(code['modified'])}." if code["modified"] else "."), "",
             f"Machine: {machine['cpu']}, {machine['cpu_count']} cores, torch threads {machine['torch_threads']}; "
             f"torch {machine['torch']}, CPU capability {machine['cpu_capability']}, "
             f"mkldnn available {machine['mkldnn_available']}, mkldnn bf16 supported "
             f"{machine['mkldnn_bf16_supported']}; /proc/cpuinfo: {flags}."
             + (f" GPU: {machine['gpu']}." if "gpu" in machine else " No GPU (`torch.cuda.is_available()` is "
                "false): CPU rows only."), "",
             "A step: forward + backward + Adam (weights and optimizer float32; bf16 = the forward under "
             "`torch.autocast(device, torch.bfloat16)`, as `trainer=bf16`); the grid's update and lookup have no "
             "backward. Ratio: float32 seconds / bf16 seconds (above 1: bf16 faster). bf16 at least as fast: by "
             "the medians; within noise: bf16 was the faster in at least a quarter of the side-by-side samples. "
             "Max rel diff: the largest relative difference of bf16's outputs from float32's on the same weights "
             f"and inputs (close: <= {CLOSE}).",
             "", "| device | component | scale | batch | fp32 s | bf16 s | ratio | bf16 at least as fast | "
             "max rel diff | close |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        diffs = ", ".join(f"{k} {v:.2g}" for k, v in r["max_rel_diff"].items())
        lines.append(f"| {r['device']} | {r['component']} | {r['scale']} | {r['batch']} | {r['fp32_s']:.4g} | "
                     f"{r['bf16_s']:.4g} | {r['fp32_over_bf16']:.2f} | {as_fast(r)} | {diffs} | "
                     f"{'yes' if r['close'] else 'NO'} |")
    slower = [r for r in rows if "grown_ops" in r]
    if slower:
        lines += ["", "## Where bf16 is slower", "",
                  f"The operators whose self time grew most (ms per step, {PROFILE_STEPS} profiled steps in each "
                  "precision). In a row marked within noise, growth of the size of the step-to-step spread "
                  "is no cost of bf16: an operator that autocast leaves in float32 runs the same in both.", ""]
        for r in slower:
            ops = "; ".join(f"`{o['op']}` {o['fp32_ms']} -> {o['bf16_ms']}" for o in r["grown_ops"])
            extra_ms = 1e3 * (r["bf16_s"] - r["fp32_s"])
            lines.append(f"- {r['device']} {r['component']} ({r['scale']}, {as_fast(r)}, {extra_ms:.3f} ms more per "
                         f"step): {ops or 'none grew'}")
    return "\n".join(lines + reading(rows)) + "\n"


def reading(rows: list[dict]) -> list[str]:
    """What the table says, in words, and what each component's bf16 can and cannot change."""
    faster = [r for r in rows if r["bf16_at_least_as_fast"]]
    by_ratio = sorted(rows, key=lambda r: r["fp32_over_bf16"])
    name = "{0[device]} {0[component]} ({0[scale]}): {0[fp32_over_bf16]:.2f}".format
    return ["", "## Reading", "",
            f"- bf16 is at least as fast in {len(faster)} of {len(rows)} rows; the smallest ratio is "
            f"{name(by_ratio[0])}, the largest {name(by_ratio[-1])}. Every bf16 output is "
            + ("within" if all(r["close"] for r in rows) else "NOT always within")
            + f" {CLOSE} of float32's (relative): bf16's speed is that of the same computation.",
            "- Autocast changes matrix products (the networks' linear layers) and little else. The hash grid "
            "encoding runs its lookups and interpolation outside autocast, in float32 (`HashGridEncoding.forward`): "
            "`hashgrid_encoding` has nothing for bf16 to speed up, and `hashgrid_field` gains only in its one "
            "hidden layer of 64 and the colour head, while the lookups and their backward stay as they are.",
            "- `occupied_at` has no matrix product: autocast casts nothing in it, and can only add its own "
            "dispatch to each of its operators, which read and write float32 in both (in its profile none grows by "
            "more than a few hundredths of a millisecond). `occupancy_update` is the field's density network without a "
            "backward pass.",
            "- The renderer's sampling and compositing stay float32 (it casts the fields' outputs back to the "
            "rays' dtype): that part of its step is the same in both."]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=21)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--threads", type=int, default=os.cpu_count())
    parser.add_argument("--only", nargs="*", default=None, help="component names to run (default: all)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    if args.repeats < 1 or args.warmup < 0 or args.threads < 1:
        parser.error(f"expected --repeats >= 1, --warmup >= 0, --threads >= 1; got {args.repeats}, {args.warmup}, "
                     f"{args.threads}")
    names = {c.name for c in components()}
    unknown = sorted(set(args.only or ()) - names)
    if unknown:
        parser.error(f"--only: expected names among {sorted(names)}, got {unknown}")
    torch.set_num_threads(args.threads)
    devices = [torch.device("cpu")] + ([torch.device("cuda")] if torch.cuda.is_available() else [])
    chosen = [c for c in components() if args.only is None or c.name in args.only]
    rows = [measure(c, device, args.warmup, args.repeats) for device in devices for c in chosen]
    machine = machine_info()
    command = "python benchmarks/kernels/precision.py" + (
        f" --repeats {args.repeats}" if args.repeats != 21 else "") + (
        f" --warmup {args.warmup}" if args.warmup != 2 else "") + (f" --threads {args.threads}") + (
        f" --only {' '.join(args.only)}" if args.only else "")
    report = {"command": command, "source": source(), "repeats": args.repeats, "warmup": args.warmup,
              "close": CLOSE, "machine": machine, "components": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write(args.out / "precision.json", (json.dumps(report, indent=2) + "\n").encode())
    text = markdown(rows, machine, report["source"], args, command)
    atomic_write(args.out / "precision.md", text.encode())
    print(text)


if __name__ == "__main__":
    main()
