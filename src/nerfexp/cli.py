"""Command-line entry points: build everything from the config, run it, nothing else."""

import logging
import sys

import hydra
import lightning as L
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from nerfexp.errors import ConfigError, NerfexpError
from nerfexp.outputs import RunRecorder

log = logging.getLogger("nerfexp")


def train(cfg: DictConfig) -> None:
    """Train on ``cfg.data``, then score the test split; everything is written to the run's directory."""
    missing = sorted(OmegaConf.missing_keys(cfg))
    if missing:
        raise ConfigError(f"missing mandatory value: {', '.join(missing)} (set it on the command line, "
                          f"e.g. {missing[0]}=...)")
    L.seed_everything(cfg.seed, workers=True)
    runtime = HydraConfig.get().runtime
    choices = {k: v for k, v in runtime.choices.items() if not k.startswith("hydra")}
    choices.update(hierarchical=cfg.hierarchical, seed=cfg.seed)
    datamodule = instantiate(cfg.datamodule)
    model = instantiate(cfg.model)
    recorder = RunRecorder(runtime.output_dir, choices, OmegaConf.to_container(cfg, resolve=True))
    callbacks = [instantiate(c) for c in cfg.callbacks.values()] + [recorder]
    trainer = instantiate(cfg.trainer, logger=instantiate(cfg.logger), callbacks=callbacks)
    trainer.fit(model, datamodule=datamodule, ckpt_path=cfg.resume)
    trainer.test(model, datamodule=datamodule, verbose=False)
    results = recorder.results
    log.info("test PSNR %.2f dB, SSIM %.4f after %d steps in %.0f s; outputs in %s", results["test_psnr"],
             results["test_ssim"], results["steps"], results["train_time_s"], recorder.output_dir)


@hydra.main(version_base=None, config_path="pkg://nerfexp.conf", config_name="config")
def main(cfg: DictConfig) -> None:
    try:
        train(cfg)
    except NerfexpError as error:  # bad input or a failed run: one line on stderr, exit status 1
        sys.exit(f"nerfexp: error: {error}")
