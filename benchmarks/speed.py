"""Speed: ``acceleration=occupancy`` against ``acceleration=none`` on the built-in scene, and where the
time of a training step goes.

Both variants train from the same seed with the same settings (the real config, ``scale=cpu`` unless
overridden), validating every ``--val-every`` steps. For each: network evaluations per ray (the mean
over training), training seconds (validation excluded), seconds per step, the
validation PSNR curve, the final test PSNR, and the time to the target PSNR: the no-grid run's final
validation PSNR minus 0.2 dB, first reached at a validation. Then K training steps of each trained model
are profiled (``torch.profiler``; on a GPU its kernels' device time): the share of a step spent in the
networks' matrix products (aten::mm, addmm, bmm: forward and backward) against the step's wall-clock
time. Runs on the GPU where there is one (Lightning's ``accelerator=auto``).

Writes ``benchmarks/results/speed.json``, ``speed.md`` and ``speed.png`` (validation PSNR against
training seconds; the step's time split into matrix products and the rest).

    python benchmarks/speed.py [--steps 2000] [--val-every 100] [--threads N] [--profile-steps 10] [override ...]

Overrides apply to both variants, except ``acceleration.*`` ones (the grid's settings), e.g.
``acceleration.grid.resolution=64``.
"""

import argparse
import json
import os
import platform
import time
from pathlib import Path

import lightning as L
import torch
import torch.nn.functional as F
from hydra import compose, initialize_config_module
from hydra.utils import instantiate
from lightning.fabric.utilities import move_data_to_device
from matplotlib.figure import Figure
from torch.profiler import ProfilerActivity, profile

from nerfexp.files import atomic_write
from nerfexp.nerf.proposal import ProposalSampler
from nerfexp.training.callbacks import FlushDenormals
from nerfexp.training.module import regularizer_sums, seeded_random
from nerfexp.training.precision import fill_precision

RESULTS = Path(__file__).parent / "results"
VARIANTS = ("none", "occupancy")
MATMUL_OPS = {"aten::mm", "aten::addmm", "aten::bmm", "aten::baddbmm", "aten::_addmm_activation"}
TARGET_MARGIN_DB = 0.2


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class TrainClock(L.Callback):
    """Training seconds with validation left out, and the mean validation PSNR over the views at each
    validation: ``curve`` [(step, training seconds, PSNR)]; ``test_psnr`` the test views' mean."""

    def __init__(self):
        self.curve: list[tuple[int, float, float]] = []
        self.train_s = 0.0
        self.test_psnr: float | None = None
        self._resumed: float | None = None
        self._psnrs: list[float] = []

    def on_validation_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0):
        self._psnrs.append(float(outputs["psnr"]))

    def on_test_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0):
        self._psnrs.append(float(outputs["psnr"]))

    def on_test_end(self, trainer, pl_module):
        self.test_psnr, self._psnrs = sum(self._psnrs) / len(self._psnrs), []

    def on_train_start(self, trainer, pl_module):
        synchronize(pl_module.device)
        self._resumed = time.perf_counter()

    def _pause(self, pl_module) -> None:
        if self._resumed is not None:
            synchronize(pl_module.device)
            self.train_s += time.perf_counter() - self._resumed
            self._resumed = None

    def on_validation_start(self, trainer, pl_module):
        self._pause(pl_module)

    def on_validation_end(self, trainer, pl_module):
        self.curve.append((trainer.global_step, self.train_s, sum(self._psnrs) / len(self._psnrs)))
        self._psnrs = []
        self._resumed = time.perf_counter()

    def on_train_end(self, trainer, pl_module):
        self._pause(pl_module)


def config(variant: str, overrides: list[str]):
    """The real config of ``variant``; overrides of ``acceleration.*`` apply to the grid's variant only."""
    if variant == "none":
        overrides = [o for o in overrides if not o.startswith("acceleration.")]
    with initialize_config_module("nerfexp.conf", version_base=None):
        return compose("config", overrides=[f"acceleration={variant}", *overrides])


def train(cfg, datamodule) -> tuple[L.LightningModule, dict]:
    """Fit and test one variant, in the config's precision (``auto`` chosen for this machine as a run
    does); the module and its numbers."""
    fill_precision(cfg)
    L.seed_everything(cfg.seed, workers=True, verbose=False)
    model = instantiate(cfg.model)
    clock = TrainClock()
    trainer = L.Trainer(accelerator="auto", devices=1, precision=cfg.trainer.precision, max_steps=cfg.trainer.max_steps,
                        val_check_interval=cfg.trainer.val_check_interval, check_val_every_n_epoch=None,
                        num_sanity_val_steps=0, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, callbacks=[FlushDenormals(), clock])
    trainer.fit(model, datamodule=datamodule)
    trainer.test(model, datamodule=datamodule, verbose=False)
    steps = trainer.global_step
    return model, {
        "precision": cfg.trainer.precision, "steps": steps, "train_s": round(clock.train_s, 2),
        "s_per_step": clock.train_s / steps,
        "evaluations_per_ray": float(model.renderer.evaluations_per_ray),
        # of which by the proposal networks (hierarchical=proposal), small density-only ones
        "proposal_samples_per_ray": (sum(model.renderer.sampler.n_samples)
                                     if isinstance(model.renderer.sampler, ProposalSampler) else 0),
        "final_val_psnr": clock.curve[-1][2], "test_psnr": clock.test_psnr,
        "curve": [{"step": s, "train_s": round(t, 2), "val_psnr": round(p, 3)} for s, t, p in clock.curve],
    }


def plain_step(model, optimizer, batch, index: int, precision: str) -> None:
    """What training step ``index`` after the grid's warm-up computes (``NeRFModule.training_step``),
    without Lightning: render, update the grid when due, the coarse + fine colour loss, backward, Adam;
    the forward under bf16 autocast where ``precision`` is ``bf16-mixed``, as Lightning runs it."""
    renderer, grid = model.renderer, model.renderer.grid
    bf16 = torch.autocast(model.device.type, dtype=torch.bfloat16, enabled=precision == "bf16-mixed")
    with bf16, seeded_random(batch.get("seed"), model.device):
        outputs = renderer(batch["origins"], batch["directions"], deterministic=False, viewdirs=batch.get("viewdirs"))
        if grid is not None:
            grid.update(grid.update_every * (grid.warmup_steps + 1) + index, renderer.density_fns())
    loss = sum(F.mse_loss(out["rgb"], batch["rgb"]) for out in outputs.values())
    loss = loss + sum(regularizer_sums(outputs).values())  # proposal losses, Ref-NeRF's penalties
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()


def profile_step(model, datamodule, n_steps: int, precision: str) -> dict:
    """Wall-clock time of ``n_steps`` plain training steps of the trained ``model`` in ``precision`` (as it
    trained: ``train``'s "precision") and the time its
    matrix products take in them (self time of ``MATMUL_OPS``; on a GPU, their kernels' device time).

    The grid is updated at the first of the steps timed and of the steps profiled (in training: every
    ``update_every`` steps), so with fewer than ``update_every`` steps its cost is overstated a little.
    The optimizer is the model's own (the config's: sparse table gradients need ``LazyAdam``)."""
    model.train()
    device = model.device
    batches = [move_data_to_device(b, device) for b, _ in zip(datamodule.train_dataloader(), range(2 * n_steps))]
    optimizer = model.optimizer(model.parameter_groups())
    for i, batch in enumerate(batches[:n_steps]):  # warm-up: allocator, kernels, caches
        plain_step(model, optimizer, batch, i + 1, precision)
    synchronize(device)
    start = time.perf_counter()
    for i, batch in enumerate(batches[n_steps:]):
        plain_step(model, optimizer, batch, i, precision)
    synchronize(device)
    step_s = (time.perf_counter() - start) / n_steps
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    with profile(activities=activities) as prof:
        for i, batch in enumerate(batches[n_steps:]):
            plain_step(model, optimizer, batch, i, precision)
        synchronize(device)
    events = prof.key_averages()
    attribute = "self_device_time_total" if device.type == "cuda" else "self_cpu_time_total"
    matmul_s = sum(getattr(e, attribute) for e in events if e.key in MATMUL_OPS) / 1e6 / n_steps
    ops_s = sum(getattr(e, attribute) for e in events) / 1e6 / n_steps
    top = sorted(events, key=lambda e: -getattr(e, attribute))[:8]
    return {
        "step_s": step_s, "matmul_s": matmul_s, "matmul_share_of_step": matmul_s / step_s,
        "matmul_share_of_op_time": matmul_s / ops_s,
        "samples_per_ray": float(model.renderer.stats["samples_per_ray"]),
        "top_ops_ms": {e.key: round(getattr(e, attribute) / 1e3 / n_steps, 2) for e in top},
    }


def time_to(curve: list[dict], target: float) -> float | None:
    """Training seconds at the first validation whose PSNR reaches ``target``; None if none does."""
    return next((point["train_s"] for point in curve if point["val_psnr"] >= target), None)


def plot(runs: dict, target: float) -> bytes:
    import io

    figure = Figure(figsize=(11.0, 4.5), layout="constrained")
    curves, bars = figure.subplots(1, 2, width_ratios=[2, 1])
    for i, (name, run) in enumerate(runs.items()):
        curves.plot([p["train_s"] for p in run["curve"]], [p["val_psnr"] for p in run["curve"]], marker=".",
                    color=f"C{i}", label=f"acceleration={name}")
        reached = run["time_to_target_s"]
        if reached is not None:
            curves.axvline(reached, color=f"C{i}", linestyle=":", linewidth=1)
    curves.axhline(target, color="k", linestyle="--", linewidth=1, label=f"target {target:.2f} dB")
    curves.set(xlabel="training seconds (validation excluded)", ylabel="validation PSNR (dB)",
               title="Quality against training time, same seed and settings")
    curves.grid(alpha=0.3)
    curves.legend(fontsize="small")
    names = list(runs)
    matmul = [runs[n]["profile"]["matmul_s"] * 1e3 for n in names]
    rest = [(runs[n]["profile"]["step_s"] - runs[n]["profile"]["matmul_s"]) * 1e3 for n in names]
    bars.bar(names, matmul, label="matrix products", color="C2")
    bars.bar(names, rest, bottom=matmul, label="everything else", color="C7")
    bars.set(ylabel="ms per training step", title="Where a step's time goes")
    bars.legend(fontsize="small")
    out = io.BytesIO()
    figure.savefig(out, format="png", dpi=100)
    return out.getvalue()


def markdown(report: dict) -> str:
    runs, summary = report["runs"], report["summary"]
    lines = ["| acceleration | evals / ray | s / step (Lightning) | plain step ms | matmul share | train s | "
             "final val PSNR | test PSNR | s to target |", "|---|---|---|---|---|---|---|---|---|"]
    for name, r in runs.items():
        p = r["profile"]
        reached = "not reached" if r["time_to_target_s"] is None else f"{r['time_to_target_s']:.1f}"
        lines.append(f"| {name} | {r['evaluations_per_ray']:.1f} | {r['s_per_step']:.4f} | {p['step_s'] * 1e3:.1f} | "
                     f"{p['matmul_share_of_step']:.0%} | {r['train_s']:.1f} | {r['final_val_psnr']:.2f} | "
                     f"{r['test_psnr']:.2f} | {reached} |")
    lines += ["", f"Target: {summary['target_psnr']:.2f} dB (the no-grid run's final validation PSNR - "
              f"{TARGET_MARGIN_DB} dB). Fewer network evaluations per ray: {summary['evaluation_ratio']:.2f}x; "
              f"time to target: {summary['time_to_target_ratio'] or 'n/a'}x less; test PSNR difference "
              f"(occupancy - none): {summary['test_psnr_difference_db']:+.2f} dB.",
              "", "Targets (2 CPU cores): " + ", ".join(f"{k}: {'met' if v else 'NOT met'}"
                                                          for k, v in summary["targets"].items()) + ".",
              "", f"Settings: {report['settings']}. Machine: {report['machine']}."]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--val-every", type=int, default=100)
    parser.add_argument("--n-val", type=int, default=4, help="validation views (the PSNR curve's noise)")
    parser.add_argument("--profile-steps", type=int, default=10)
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("overrides", nargs="*", help="config overrides for both variants (acceleration.*: the grid's)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    overrides = [f"scale.steps={args.steps}", f"scale.val_every={args.val_every}", f"data.n_val={args.n_val}",
                 *args.overrides]
    datamodule = None
    runs = {}
    for variant in VARIANTS:
        cfg = config(variant, overrides)
        datamodule = datamodule or instantiate(cfg.datamodule)  # the scene is rendered once
        model, runs[variant] = train(cfg, datamodule)
        runs[variant]["profile"] = profile_step(model, datamodule, args.profile_steps, runs[variant]["precision"])
        print(variant, {k: v for k, v in runs[variant].items() if k != "curve"}, flush=True)
    target = runs["none"]["final_val_psnr"] - TARGET_MARGIN_DB
    for run in runs.values():
        run["time_to_target_s"] = time_to(run["curve"], target)
    none, occupancy = runs["none"], runs["occupancy"]
    ratio = (none["time_to_target_s"] / occupancy["time_to_target_s"]
             if none["time_to_target_s"] and occupancy["time_to_target_s"] else None)
    summary = {
        "target_psnr": target,
        "evaluation_ratio": none["evaluations_per_ray"] / occupancy["evaluations_per_ray"],
        "time_to_target_ratio": None if ratio is None else round(ratio, 2),
        "test_psnr_difference_db": occupancy["test_psnr"] - none["test_psnr"],
    }
    summary["targets"] = {
        "3x fewer evaluations per ray": summary["evaluation_ratio"] >= 3,
        "2x less time to the target PSNR": ratio is not None and ratio >= 2,
        "test PSNR at most 0.2 dB lower": summary["test_psnr_difference_db"] >= -TARGET_MARGIN_DB,
        "matmul >= 70% of the no-grid step": none["profile"]["matmul_share_of_step"] >= 0.7,
    }
    machine = {"cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
               "processor": platform.processor() or platform.machine(), "torch": torch.__version__,
               "cuda": torch.cuda.get_device_name() if torch.cuda.is_available() else None}
    report = {"machine": machine, "settings": {"overrides": overrides, "profile_steps": args.profile_steps},
              "runs": runs, "summary": summary}
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write(args.out / "speed.json", (json.dumps(report, indent=2) + "\n").encode())
    atomic_write(args.out / "speed.md", markdown(report).encode())
    atomic_write(args.out / "speed.png", plot(runs, target))
    print(markdown(report))


if __name__ == "__main__":
    main()
