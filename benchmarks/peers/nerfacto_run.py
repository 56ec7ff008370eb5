"""nerfstudio's nerfacto trained on one scene, its test views rendered at chosen training times: the peer half of
benchmarks/peers/compare.py. Runs in nerfstudio's own environment (``pip install nerfstudio`` into a venv of its
own), not nerfexp's:

    PEER_PYTHON benchmarks/peers/nerfacto_run.py OUT --budgets 60 120 300 -- NS_TRAIN_ARGS...

NS_TRAIN_ARGS are ``ns-train``'s own arguments after the method's name (``--machine.device-type cpu ...
blender-data --data DIR``), parsed by nerfstudio's own command-line parser, so the run is the one ``ns-train
nerfacto NS_TRAIN_ARGS`` makes. The training clock counts nerfstudio's training iterations (``Trainer.train_iteration``: the
batch, forward, backward and optimizer step), not the setup before the first step, the callbacks between steps
(the proposal sampler's annealing) nor the renders: at each budget (seconds
of that clock) the clock stops, every test view is rendered (``Model.get_outputs_for_camera``) and written as an
8-bit PNG ``OUT/budget_K/NAME.png`` (NAME: the test image's file stem), and the clock goes on. Writes
``OUT/nerfacto.json``: per budget the step and the clock's seconds, the threads, torch's version, the arguments.
Scores are computed by compare.py with nerfexp's code, not here.
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torchmetrics.image.lpip
import tyro
from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion
from PIL import Image


class NoLPIPS(torch.nn.Module):
    """Stands for torchmetrics' LPIPS in nerfacto: nerfacto builds it when the model is made (its evaluation metric),
    which downloads AlexNet's ImageNet weights, and this machine cannot reach them. Training never calls it; the
    scores are nerfexp's (compare.py), so it refuses to be called rather than score."""

    def __init__(self, *args, **kwargs):
        super().__init__()

    def forward(self, *args, **kwargs):
        raise RuntimeError("LPIPS is not scored by this driver (no AlexNet weights here): compare.py scores renders")


def render_test_views(trainer, out: Path) -> int:
    """Each test view of the trainer's eval data rendered and written to ``out`` as ``NAME.png`` (8 bits, rounded);
    the number written."""
    datamanager = trainer.pipeline.datamanager
    names = [Path(p).stem for p in datamanager.eval_dataset._dataparser_outputs.image_filenames]
    out.mkdir(parents=True, exist_ok=True)
    model = trainer.pipeline.model
    model.eval()
    written = 0
    with torch.no_grad():
        for camera, batch in datamanager.fixed_indices_eval_dataloader:
            rgb = model.get_outputs_for_camera(camera)["rgb"].clamp(0, 1)  # [H, W, 3]
            pixels = (rgb.cpu().numpy() * 255 + 0.5).astype(np.uint8)
            Image.fromarray(pixels).save(out / f"{names[int(batch['image_idx'])]}.png")
            written += 1
    model.train()
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--budgets", type=float, nargs="+", required=True, help="seconds of training, increasing")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--seed", type=int, default=0)
    args, rest = parser.parse_known_args()
    ns_args = rest[1:] if rest[:1] == ["--"] else rest
    torchmetrics.image.lpip.LearnedPerceptualImagePatchSimilarity = NoLPIPS  # imported from there at model build
    if args.threads:
        torch.set_num_threads(args.threads)
    config = tyro.cli(AnnotatedBaseConfigUnion, args=["nerfacto", *ns_args])
    config.machine.seed = args.seed
    config.output_dir = args.out / "ns_outputs"
    config.set_timestamp()
    config.save_config()
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup(test_mode="test")

    budgets = sorted(args.budgets)
    record = {"tool": "nerfstudio nerfacto", "torch": torch.__version__, "threads": torch.get_num_threads(),
              "ns_train_args": ["nerfacto", *ns_args], "seed": args.seed, "budgets": []}
    clock = 0.0
    iteration = trainer.train_iteration

    def timed(step: int):
        nonlocal clock
        start = time.perf_counter()
        result = iteration(step)
        clock += time.perf_counter() - start
        while budgets and clock >= budgets[0]:
            budget = budgets.pop(0)
            folder = args.out / f"budget_{len(record['budgets'])}"
            n = render_test_views(trainer, folder)
            record["budgets"].append({"budget_s": budget, "train_s": clock, "step": step + 1, "folder": folder.name,
                                      "views": n})
            print(f"nerfacto: {clock:.1f} s, step {step + 1}: {n} test views rendered to {folder}", flush=True)
            if not budgets:
                trainer.stop_training = True
        return result

    trainer.train_iteration = timed
    trainer.train()
    (args.out / "nerfacto.json").write_text(json.dumps(record, indent=1))
    if budgets:
        sys.exit(f"nerfacto stopped at its max-num-iterations before the budgets {budgets}")


if __name__ == "__main__":
    main()
