"""Sparse hash-table gradients with LazyAdam against dense gradients with torch.optim.Adam: the cost of a
training step as the table grows. Writes benchmarks/results/sparse_tables.{json,md}.

One training step of the hash grid's field from the real config (``encoding=hashgrid`` at
``scale=cpu``: 16 levels of 2 features, 16 to 256 cells, its 1 x 64 network and the colour head of
``view_dependence``), one network of 96 samples per ray (``hierarchical=false``) on ``--rays`` rays of the
built-in scene: render, colour loss, backward, optimizer step, with the optimizer's parameter groups
(``NeRFModule.parameter_groups``), for each ``--log2-table-sizes`` and both variants:
- ``dense``: ``model.optimizer._target_=torch.optim.Adam encoding.position.sparse_gradients=false``;
- ``lazy``: ``model.optimizer._target_=nerfexp.training.optimizers.LazyAdam encoding.position.sparse_gradients=true``.
The median of ``--repeats`` steps after ``--warmup`` steps, each variant from the same weights and on the
same batches, their steps alternating; the forward and backward pass and the optimizer step are timed
apart. Levels whose vertices fit the table are dense (``F.grid_sample`` volumes) and keep dense gradients
in both variants; the table rows of the hashed levels, and the rows one step touches, are counted.

The quality of whole runs is a sweep and the report: ``nerfexp +sweeps=sparse_tables`` (its file says how
to report it; docs/results/sparse_tables/).

    python benchmarks/kernels/sparse_tables.py [--log2-table-sizes 14 16 19 22] [--repeats 10] [--warmup 3]
                                               [--threads N]
"""

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import torch
import torch.nn.functional as F
from hydra import compose, initialize_config_module
from hydra.utils import instantiate

from nerfexp.files import atomic_write
from nerfexp.nerf.bounds import Bounded
from nerfexp.nerf.hashgrid import HashGridEncoding

RESULTS = Path(__file__).parents[1] / "results"  # benchmarks/results
VARIANTS = {
    "dense": ["model.optimizer._target_=torch.optim.Adam", "encoding.position.sparse_gradients=false"],
    "lazy": ["model.optimizer._target_=nerfexp.training.optimizers.LazyAdam",
             "encoding.position.sparse_gradients=true"],
}
SAMPLES = 96  # per ray: scale=cpu's hierarchical model evaluates 24 + (24 + 48)


def model_and_optimizer(log2_table_size: int, variant: str, rays: int):
    """The real config's model (one network of SAMPLES samples) and its optimizer, for ``variant``."""
    overrides = ["encoding=hashgrid", "hierarchical=false", f"scale.n_single={SAMPLES}", f"scale.batch_rays={rays}",
                 f"encoding.position.log2_table_size={log2_table_size}", *VARIANTS[variant]]
    with initialize_config_module("nerfexp.conf", version_base=None):
        cfg = compose("config", overrides=overrides)
    torch.manual_seed(0)
    model = instantiate(cfg.model)
    return cfg, model, model.optimizer(model.parameter_groups())


def timed_step(model, optimizer, batch: dict) -> tuple[float, float]:
    """Seconds of one training step's forward and backward pass, and of its optimizer step."""
    start = time.perf_counter()
    outputs = model.renderer(batch["origins"], batch["directions"], deterministic=False,
                             viewdirs=batch.get("viewdirs"))
    loss = sum(F.mse_loss(out["rgb"], batch["rgb"]) for out in outputs.values())
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    middle = time.perf_counter()
    optimizer.step()
    return middle - start, time.perf_counter() - middle


def rows_touched(model) -> int | None:
    """The rows of the hashed tables that the last step's sparse gradients hold; None for dense ones."""
    grads = [m.hashed.grad for m in model.renderer.modules() if isinstance(m, HashGridEncoding)]
    return sum(grad._nnz() for grad in grads) if all(grad.is_sparse for grad in grads) else None


def speed(args) -> list[dict]:
    """For each table size, both variants from the same weights on the same batches, their steps
    alternating (dense, lazy, dense, ...), so that the machine's drifts touch both alike."""
    rows = []
    for log2 in args.log2_table_sizes:
        built = {variant: model_and_optimizer(log2, variant, args.rays) for variant in VARIANTS}
        cfg, model, _ = built["dense"]
        datamodule = instantiate(cfg.datamodule)
        datamodule.setup("fit")
        loader = iter(datamodule.train_dataloader())
        batches = [next(loader) for _ in range(args.warmup + args.repeats)]
        box = datamodule.scene_box(model.renderer.near, model.renderer.far)
        for _, model, _ in built.values():
            for module in model.renderer.modules():
                if isinstance(module, Bounded):
                    module.set_bounds(box)
        times = {variant: [] for variant in VARIANTS}
        for i, batch in enumerate(batches):
            for variant, (_, model, optimizer) in built.items():
                seconds = timed_step(model, optimizer, batch)
                if i >= args.warmup:
                    times[variant].append(seconds)
        encoding = built["lazy"][1].renderer.coarse.position_encoding
        row = {"log2_table_size": log2, "hashed_levels": encoding.hashed.shape[0],
               "table_rows": encoding.hashed[..., 0].numel(),
               "dense_level_entries": sum(v.numel() for v in encoding.dense)}
        for variant, pairs in times.items():
            row[variant] = {"step_s": statistics.median(p + u for p, u in pairs),
                            "forward_backward_s": statistics.median(p for p, _ in pairs),
                            "optimizer_s": statistics.median(u for _, u in pairs),
                            "rows_touched": rows_touched(built[variant][1])}
            print(log2, variant, row[variant], flush=True)
        row["lazy_over_dense"] = row["lazy"]["step_s"] / row["dense"]["step_s"]
        rows.append(row)
        del built
    return rows


def markdown(report: dict, args) -> str:
    lines = [f"One training step of the hash grid's field ({args.rays} rays x {SAMPLES} samples, "
             f"`encoding=hashgrid` at `scale=cpu`, one network): median of {args.repeats} after {args.warmup} "
             "warm-up steps, seconds.", "",
             "| log2 T | hashed levels | table rows | rows touched | dense-level entries | dense Adam step | "
             "LazyAdam step | ratio | dense Adam: optimizer | LazyAdam: optimizer |", "|---" * 10 + "|"]
    for row in report["speed"]:
        dense, lazy = row["dense"], row["lazy"]
        lines.append(f"| {row['log2_table_size']} | {row['hashed_levels']} | {row['table_rows']} | "
                     f"{lazy['rows_touched']} | {row['dense_level_entries']} | {dense['step_s']:.3f} | "
                     f"{lazy['step_s']:.3f} | {row['lazy_over_dense']:.2f} | {dense['optimizer_s']:.3f} | "
                     f"{lazy['optimizer_s']:.3f} |")
    lines += ["", f"Command: `python benchmarks/kernels/sparse_tables.py --log2-table-sizes "
              f"{' '.join(map(str, args.log2_table_sizes))} --repeats {args.repeats} --warmup {args.warmup}"
              + (f" --threads {args.threads}" if args.threads else "") + "`."]
    lines += ["", f"Machine: {report['machine']}."]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--log2-table-sizes", type=int, nargs="+", default=[14, 16, 19, 22])
    parser.add_argument("--rays", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.set_flush_denormal(True)  # as in training (nerfexp.training.callbacks.FlushDenormals)
    machine = {"cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
               "processor": platform.processor() or platform.machine(), "torch": torch.__version__}
    report = {"machine": machine, "rays": args.rays, "samples": SAMPLES, "repeats": args.repeats,
              "warmup": args.warmup, "speed": speed(args)}
    text = markdown(report, args)
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write(args.out / "sparse_tables.json", (json.dumps(report, indent=2) + "\n").encode())
    atomic_write(args.out / "sparse_tables.md", text.encode())
    print(text)


if __name__ == "__main__":
    main()
