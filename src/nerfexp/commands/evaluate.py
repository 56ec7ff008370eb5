"""``nerfexp-eval RUN_DIR``: score a run's checkpoint on its test split, with the config the run used."""

import argparse
from pathlib import Path

from hydra.utils import instantiate
from omegaconf import DictConfig

from nerfexp.commands.arguments import add_run_arguments, command_parser, run_settings, say_unfinished
from nerfexp.commands.console import run_command
from nerfexp.manifest import check_ours
from nerfexp.products.trained import load_module
from nerfexp.rundir.layout import EVAL, read_json
from nerfexp.rundir.trained import find_run


def evaluate(cfg: DictConfig, run_dir: Path, checkpoint: Path) -> dict:
    """Score ``checkpoint`` on the test split of the run's data (``cfg``, the run's config), without
    training, on the run's trainer (``trainer=ddp``: its processes share the images); the scores go to
    ``RUN_DIR/eval.json`` (see ``EvalRecorder``) and are returned."""
    # with Lightning: imported here, so that a missing run or a bad override is said without waiting for it
    from nerfexp.training.precision import fill_precision
    from nerfexp.training.progress import progress_bars
    from nerfexp.training.recorders import EvalRecorder

    fill_precision(cfg)
    model, step = load_module(cfg, checkpoint)
    say_unfinished("nerfexp-eval", run_dir, checkpoint, step)
    recorder = EvalRecorder(run_dir, checkpoint, step)
    trainer = instantiate(cfg.trainer, logger=False, callbacks=[recorder, *progress_bars(cfg.trainer)],
                          enable_checkpointing=False, default_root_dir=str(run_dir))
    trainer.test(model, datamodule=instantiate(cfg.datamodule), verbose=False)
    return read_json(run_dir / EVAL)


def build_parser() -> argparse.ArgumentParser:
    """``nerfexp-eval RUN_DIR`` (or a checkpoint file in it): score the run's checkpoint on its test split
    with the config the run used, and write the scores to RUN_DIR/eval.json."""
    parser = command_parser("nerfexp-eval", build_parser.__doc__)
    add_run_arguments(parser)
    return parser


def evaluate_run(run: Path, overrides: list[str]) -> str:
    """Score the run at ``run`` (a run directory or a checkpoint file in one) with its saved config changed
    by ``overrides`` (``evaluate``), its settings checked first (``run_settings``); returns a one-line summary.
    An ``eval.json`` there that the run directory's manifest does not show to be nerfexp's
    (``nerfexp.manifest.check_ours``) is refused first."""
    run_dir, checkpoint = find_run(run)
    check_ours(run_dir, [EVAL], "nerfexp-eval", "move {it} elsewhere: nerfexp-eval writes its scores there")
    results = evaluate(run_settings(run_dir, overrides), run_dir, checkpoint)
    from nerfexp.training.recorders import scores_text  # imports Lightning: not before bad input is refused
    return f"{scores_text(results)} of {checkpoint} (step {results['step']}); written to {run_dir / EVAL}"


def main(argv: list[str] | None = None) -> None:
    """The ``nerfexp-eval`` command (``build_parser``)."""
    run_command(build_parser(), argv, lambda args: evaluate_run(args.run, args.overrides))


if __name__ == "__main__":
    main()
