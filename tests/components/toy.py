"""A component from outside nerfexp, added by the recipe in docs/developing.md: a toy encoding (the tests'
own), its config in ``tests/components/encoding/toy.yaml`` found through ``hydra.searchpath``."""

from collections.abc import Mapping

from torch import Tensor

from nerfexp.domains import COUNT, real
from nerfexp.nerf.encodings import Encoding


class PowerEncoding(Encoding):
    """(x, x^2, ..., x^n_powers) of each coordinate, each times ``gain``: a polynomial feature map."""

    DOMAINS = {"n_powers": COUNT, "gain": real(0, 16, above=True)}
    TOP_POWER = 8  # with a gain above 1, x^n of positions a few units across outgrows the others beyond it
    # its arguments that must fit together (nerfexp.domains): asked by the settings check, named as the user sets them
    CONSISTENT = {("n_powers", "gain"): lambda config: None if config["gain"] <= 1 or config["n_powers"] <= 8
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
