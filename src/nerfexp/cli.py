"""Command-line entry points: build everything from the config, run it, nothing else."""

import logging
import sys

import hydra
import lightning as L
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from nerfexp.errors import ConfigError, NerfexpError
from nerfexp.outputs import RunRecorder, write_status

log = logging.getLogger("nerfexp")


def train(cfg: DictConfig) -> dict:
    """Train on ``cfg.data``, then score the test split; everything is written to the run's directory.
    Returns the run's results (see ``RunRecorder``)."""
    missing = sorted(OmegaConf.missing_keys(cfg))
    if missing:
        raise ConfigError(f"missing mandatory value: {', '.join(missing)} (set it on the command line, "
                          f"e.g. {missing[0]}=...)")
    L.seed_everything(cfg.seed, workers=True)
    runtime = HydraConfig.get().runtime
    choices = {k: v for k, v in runtime.choices.items() if not k.startswith("hydra") and v is not None}
    choices.update(hierarchical=cfg.hierarchical, seed=cfg.seed)
    datamodule = instantiate(cfg.datamodule)
    model = instantiate(cfg.model)
    overrides = list(HydraConfig.get().overrides.task)
    recorder = RunRecorder(runtime.output_dir, choices, OmegaConf.to_container(cfg, resolve=True), overrides)
    callbacks = [instantiate(c) for c in cfg.callbacks.values()] + [recorder]
    trainer = instantiate(cfg.trainer, logger=instantiate(cfg.logger), callbacks=callbacks)
    trainer.fit(model, datamodule=datamodule, ckpt_path=cfg.resume)
    trainer.test(model, datamodule=datamodule, verbose=False)
    results = recorder.results
    log.info("test PSNR %.2f dB, SSIM %.4f after %d steps in %.0f s; outputs in %s", results["test_psnr"],
             results["test_ssim"], results["steps"], results["train_time_s"], recorder.output_dir)
    return results


@hydra.main(version_base=None, config_path="pkg://nerfexp.conf", config_name="config")
def main(cfg: DictConfig) -> float | None:
    """Run one job; its status goes to ``status.json``. Returns the last validation PSNR, which a
    hyper-parameter sweeper (``+sweeps=optuna``) maximizes.

    A single run with bad input ends with one line on stderr and exit status 1. In a multirun the
    error is raised instead, so that Hydra records this job as failed and goes on with the others
    (the sweep then ends with the first job's error; ``nerfexp-report`` lists the failed jobs)."""
    hydra_config = HydraConfig.get()
    output_dir, overrides = hydra_config.runtime.output_dir, list(hydra_config.overrides.task)
    write_status(output_dir, "running", overrides)
    try:
        results = train(cfg)
    except BaseException as error:  # an interrupt too: the job did not finish
        write_status(output_dir, "failed", overrides, error=f"{type(error).__name__}: {error}")
        if isinstance(error, NerfexpError):
            if hydra_config.mode == RunMode.RUN:
                sys.exit(f"nerfexp: error: {error}")
            log.error("job failed: %s", error)
        raise
    write_status(output_dir, "finished", overrides)
    return results["val_psnr"]
