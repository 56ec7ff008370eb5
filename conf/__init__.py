"""nerfexp's config groups (a package so that Hydra finds them as ``pkg://nerfexp.conf``), and the one
resolver they use, registered when Hydra imports this package to read them."""

from omegaconf import OmegaConf


def gpus_per_node(accelerator: str, devices: int) -> int | None:
    """The GPUs a SLURM job asks for on each node (``conf/hydra/launcher/slurm.yaml``): one per process,
    none where the processes run on the CPU (``trainer.accelerator=cpu``: gloo), whose ``--gpus-per-node``
    a cluster without GPUs refuses."""
    return None if accelerator == "cpu" else devices


OmegaConf.register_new_resolver("nerfexp.gpus_per_node", gpus_per_node, replace=True)
