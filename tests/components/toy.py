"""A component from outside nerfexp, added by the recipe in docs/developing.md: a toy encoding (the tests'
own), its config in ``tests/components/encoding/toy.yaml`` found through ``hydra.searchpath``."""

from torch import Tensor

from nerfexp.domains import COUNT, real
from nerfexp.nerf.encodings import Encoding


class PowerEncoding(Encoding):
    """(x, x^2, ..., x^n_powers) of each coordinate, each times ``gain``: a polynomial feature map."""

    DOMAINS = {"n_powers": COUNT, "gain": real(0, 16, above=True)}

    def __init__(self, n_powers: int = 2, gain: float = 1.0, in_dim: int = 3):
        super().__init__()
        self.n_powers, self.gain, self.in_dim = n_powers, gain, in_dim
        self.out_dim = in_dim * n_powers

    def forward(self, x: Tensor) -> Tensor:
        """x [..., D] -> [..., D * n_powers]."""
        return self.gain * x.unsqueeze(-2).pow(x.new_tensor(range(1, self.n_powers + 1))[:, None]).flatten(-2)
