"""``nerfexp-eval RUN_DIR``: score a run's checkpoint on its test split, with the config the run used."""

import argparse
from pathlib import Path

from hydra.utils import instantiate
from omegaconf import DictConfig

from nerfexp.arguments import add_run_arguments, command_parser, one_line_errors
from nerfexp.console import quiet_dependencies
from nerfexp.rundir import EVAL, find_run, load_module, read_json, run_config
from nerfexp.training.recorders import EvalRecorder


def evaluate(cfg: DictConfig, run_dir: Path, checkpoint: Path) -> dict:
    """Score ``checkpoint`` on the test split of the run's data (``cfg``, the run's config), without
    training, on the run's trainer (``trainer=ddp``: its processes share the images); the scores go to
    ``RUN_DIR/eval.json`` (see ``EvalRecorder``) and are returned."""
    model, step = load_module(cfg, checkpoint)
    recorder = EvalRecorder(run_dir, checkpoint, step)
    trainer = instantiate(cfg.trainer, logger=False, callbacks=[recorder], enable_checkpointing=False,
                          default_root_dir=str(run_dir))
    trainer.test(model, datamodule=instantiate(cfg.datamodule), verbose=False)
    return read_json(run_dir / EVAL)


def build_parser() -> argparse.ArgumentParser:
    """``nerfexp-eval RUN_DIR`` (or a checkpoint file in it): score the run's checkpoint on its test split
    with the config the run used, and write the scores to RUN_DIR/eval.json."""
    parser = command_parser("nerfexp-eval", build_parser.__doc__)
    add_run_arguments(parser)
    return parser


def main(argv: list[str] | None = None) -> None:
    """The ``nerfexp-eval`` command (``build_parser``)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    quiet_dependencies()
    with one_line_errors(parser.prog):
        run_dir, checkpoint = find_run(args.run)
        results = evaluate(run_config(run_dir, args.overrides), run_dir, checkpoint)
    print(f"test PSNR {results['test_psnr']:.2f} dB, SSIM {results['test_ssim']:.4f} of {checkpoint} "
          f"(step {results['step']}); written to {run_dir / EVAL}")


if __name__ == "__main__":
    main()
