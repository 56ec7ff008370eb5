"""Trainer choices and Hydra launchers: mixed precision, SLURM through submitit (its config and Lightning's
SLURM environment), and a sweep run in parallel by the submitit local launcher."""

import os
from unittest import mock

import lightning as L
import lightning_utilities.core.rank_zero as utilities_rank_zero
import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate
from lightning.fabric.plugins.environments import SLURMEnvironment
from lightning.fabric.utilities import rank_zero as fabric_rank_zero
from omegaconf import OmegaConf

import nerfexp.nerf.volume_renderer as renderer_module
from nerfexp.training.precision import fill_precision
from tests.helpers import TINY, read_json, run_nerfexp


def config(*overrides: str, hydra: bool = False):
    with initialize_config_module("nerfexp.conf", version_base=None):
        return compose("config", overrides=list(overrides), return_hydra_config=hydra)


def test_slurm_launcher_asks_for_a_task_and_a_gpu_per_device_on_every_node():
    cfg = config("hydra/launcher=slurm", "trainer=slurm", "trainer.devices=4", "trainer.num_nodes=2",
                 "hydra.launcher.partition=gpu", hydra=True)
    launcher = OmegaConf.to_container(cfg.hydra.launcher, resolve=True)
    assert launcher["_target_"].endswith("submitit_launcher.SlurmLauncher")
    assert (launcher["nodes"], launcher["tasks_per_node"], launcher["gpus_per_node"]) == (2, 4, 4)
    assert launcher["partition"] == "gpu" and launcher["timeout_min"] > 0
    assert (cfg.trainer.strategy, cfg.trainer.accelerator, cfg.trainer.num_nodes) == ("ddp", "gpu", 2)
    assert config("trainer=ddp").trainer.strategy == "ddp_spawn"


def test_slurm_jobs_of_cpu_processes_ask_for_no_gpus():
    cfg = config("hydra/launcher=slurm", "trainer=slurm", "trainer.accelerator=cpu", "trainer.devices=2", hydra=True)
    launcher = OmegaConf.to_container(cfg.hydra.launcher, resolve=True)
    assert (launcher["tasks_per_node"], launcher["gpus_per_node"]) == (2, None)  # sbatch: no --gpus-per-node


SLURM_TASK = {  # what srun sets for task 3 of a job of 2 nodes x 2 tasks
    "SLURM_NTASKS": "4", "SLURM_NTASKS_PER_NODE": "2", "SLURM_NNODES": "2", "SLURM_PROCID": "3",
    "SLURM_LOCALID": "1", "SLURM_NODEID": "1", "SLURM_NODELIST": "gpu[07-08]", "SLURM_JOB_ID": "4242",
    "SLURM_JOB_NAME": "nerfexp",
}


# the whole environment put back after the test: Lightning writes MASTER_ADDR (gpu07) into it, which would
# reach every distributed run the test session starts later
@mock.patch.dict(os.environ)
def test_under_slurm_lightning_joins_the_processes_srun_started(monkeypatch):
    for key, value in SLURM_TASK.items():
        monkeypatch.setenv(key, value)
    for module in (utilities_rank_zero, fabric_rank_zero):  # the trainer sets this process's rank: put it back
        monkeypatch.setattr(module.rank_zero_only, "rank", module.rank_zero_only.rank)
    cfg = config("trainer=slurm", "trainer.accelerator=cpu", "trainer.devices=2", "trainer.num_nodes=2")
    fill_precision(cfg)  # as a job does before it builds the trainer
    trainer = instantiate(cfg.trainer, logger=False, callbacks=[], default_root_dir=".", max_steps=1)
    environment = trainer.strategy.cluster_environment
    assert isinstance(environment, SLURMEnvironment) and environment.creates_processes_externally
    assert (trainer.global_rank, trainer.local_rank, trainer.node_rank, trainer.world_size) == (3, 1, 1, 4)
    assert environment.main_address == "gpu07"  # rank 0's node, where every process connects


def test_bf16_trains_with_float32_rendering(monkeypatch, tmp_path):
    rendered = []
    original = renderer_module.render_weights

    def recording(sigmas, t_starts, t_ends):
        rendered.append(sigmas.dtype)
        return original(sigmas, t_starts, t_ends)

    monkeypatch.setattr(renderer_module, "render_weights", recording)
    cfg = config(*TINY, "trainer=bf16", "scale.steps=4", "trainer.accelerator=cpu")
    assert cfg.trainer.precision == "bf16-mixed"
    L.seed_everything(0)
    model, datamodule = instantiate(cfg.model), instantiate(cfg.datamodule)
    network = set()
    model.renderer.coarse.trunk[0].register_forward_hook(lambda module, inputs, out: network.add(out.dtype))
    trainer = instantiate(cfg.trainer, logger=False, callbacks=[], enable_checkpointing=False,
                          default_root_dir=str(tmp_path), limit_val_batches=0)
    trainer.fit(model, datamodule=datamodule)
    assert trainer.global_step == 4 and torch.bfloat16 in network  # the network ran under bf16 autocast
    assert rendered and set(rendered) == {torch.float32}  # the volume rendering did not
    assert all(torch.isfinite(p).all() and p.dtype == torch.float32 for p in model.parameters())


@pytest.mark.slow
def test_a_sweep_through_the_submitit_local_launcher(tmp_path):
    sweep = tmp_path / "sweep"
    done = run_nerfexp("-m", "hydra/launcher=submitit_local", *TINY, "scale.steps=10", "scale.val_every=10",
                       "seed=0,1", f"hydra.sweep.dir={sweep}", new_process=True, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    assert sorted(p.name for p in sweep.iterdir()) == [".submitit", "0", "1", "multirun.yaml"]
    for job in (0, 1):
        results = read_json(sweep / str(job) / "results.json")
        assert results["steps"] == 10 and results["choices"]["seed"] == job
        assert read_json(sweep / str(job) / "status.json")["state"] == "finished"
