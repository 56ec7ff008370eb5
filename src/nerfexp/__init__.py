"""nerfexp: a config-driven experiment and ablation framework for NeRF."""
