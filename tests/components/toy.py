"""Components from outside nerfexp, each added by its recipe in docs/developing.md: a toy encoding, a toy colour
head and a toy sampler (the tests' own), their configs in ``tests/components/GROUP/toy.yaml`` found through
``hydra.searchpath``."""

from collections.abc import Mapping

import torch
from torch import Tensor, nn

from nerfexp.domains import COUNT, real
from nerfexp.nerf.encodings import Encoding
from nerfexp.nerf.fields import ViewDependence
from nerfexp.nerf.samplers import Rays, Sampler, Steps


class PowerEncoding(Encoding):
    """(x, x^2, ..., x^n_powers) of each coordinate, each times ``gain``: a polynomial feature map."""

    DOMAINS = {"n_powers": COUNT, "gain": real(0, 16, above=True)}
    TOP_POWER = 8  # with a gain above 1, x^n of positions a few units across outgrows the others beyond it
    # its arguments that must fit together (nerfexp.domains): asked by the settings check, named as the user sets them
    CONSISTENT = {("n_powers", "gain"): lambda config: None if config["gain"] <= 1 or config["n_powers"] <= PowerEncoding.TOP_POWER
                  else f"{PowerEncoding.TOP_POWER} powers at most with a gain above 1"}

    @staticmethod
    def MEMORY(config: Mapping) -> list[tuple[tuple[str, ...], str, int]]:
        """Its exponents, a float32 each (what building it holds, for the settings' memory check)."""
        return [(("n_powers",), f"the exponents of {config['n_powers']} powers", 4 * config["n_powers"])]

    def __init__(self, n_powers: int = 2, gain: float = 1.0, in_dim: int = 3):
        super().__init__()
        self.n_powers, self.gain, self.in_dim = n_powers, gain, in_dim
        self.out_dim = in_dim * n_powers

    def forward(self, x: Tensor) -> Tensor:
        """x [..., D] -> [..., D * n_powers]."""
        return self.gain * x.unsqueeze(-2).pow(x.new_tensor(range(1, self.n_powers + 1))[:, None]).flatten(-2)


class TiltViewDependence(ViewDependence):
    """rgb = sigmoid(W h + b + tilt d): a linear colour of the trunk's features, tilted channel by channel by the
    view direction's coordinates (red by d_x, green by d_y, blue by d_z): the simplest view-dependent head."""

    DOMAINS = {"tilt": real(-8, 8)}

    def __init__(self, in_features: int, tilt: float = 1.0):
        super().__init__()
        self.rgb = nn.Linear(in_features, 3)
        self.tilt = tilt

    def forward(self, h: Tensor, directions: Tensor) -> Tensor:
        """h [..., S, F], directions [..., S or 1, 3] -> rgb [..., S, 3]."""
        return torch.sigmoid(self.rgb(h) + self.tilt * directions)


class MidpointSampler(Sampler):
    """One field at the midpoints of ``n_samples`` equal bins of [near, far], never jittered:
    t_i = near + (i + 1/2) (far - near) / n_samples."""

    DOMAINS = {"n_samples": COUNT}

    def __init__(self, n_samples: int):
        super().__init__()
        self.n_samples = n_samples

    @staticmethod
    def SAMPLES_PER_RAY(config: Mapping) -> tuple[int, tuple[str, ...]]:
        return config["n_samples"], ("n_samples",)

    @property
    def samples_per_ray(self) -> int:
        return self.n_samples

    def render(self, rays: Rays, steps: Steps, deterministic: bool) -> dict[str, dict[str, Tensor]]:
        fractions = (torch.arange(self.n_samples, dtype=rays.near.dtype, device=rays.near.device) + 0.5) / self.n_samples
        t = rays.near[:, None] + (rays.far - rays.near)[:, None] * fractions  # [B, n_samples]
        return {"coarse": steps.composited("coarse", rays, t)}
