"""One step of the lazy Adam kernel, for the kernel cache's tests and the processes they start."""

import torch


def adam_rows(module) -> torch.Tensor:
    """One touched-rows Adam step of a 4 x 3 parameter by ``module`` (rows 0 and 2): the parameter after it."""
    param, m, v = torch.ones(4, 3), torch.zeros(4, 3), torch.zeros(4, 3)
    module.rows(param, m, v, torch.tensor([0, 2]), torch.full((2, 3), 0.5), 1.0, 0.1, 0.9, 0.999, 1e-8)
    return param
