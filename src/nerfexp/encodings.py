"""Input encodings for the field: each maps [..., in_dim] to [..., out_dim] and reports ``out_dim``."""

import torch
from torch import Tensor, nn


class IdentityEncoding(nn.Module):
    """Raw coordinates, unchanged: the "No Pos. Encoding" ablation."""

    def __init__(self, in_dim: int = 3):
        super().__init__()
        self.in_dim = in_dim
        self.out_dim = in_dim

    def forward(self, x: Tensor) -> Tensor:
        return x


class PositionalEncoding(nn.Module):
    """gamma(p) = (p, sin(2^0 pi p), cos(2^0 pi p), ..., sin(2^(L-1) pi p), cos(2^(L-1) pi p)).

    Applied per coordinate, L = ``n_freqs``; the raw input comes first when ``include_input``.
    Output layout for x [..., D]: [x | sin(pi 2^k x_d) for k, d | cos(pi 2^k x_d) for k, d], so
    ``out_dim = D * (include_input + 2 L)``: 63 for positions with L = 10, 27 for directions with L = 4.

    >>> PositionalEncoding(n_freqs=1)(torch.tensor([[0.5, 0.0, 0.0]]))[0, 3:6]  # sin(pi x)
    tensor([1., 0., 0.])
    """

    def __init__(self, n_freqs: int, in_dim: int = 3, include_input: bool = True):
        super().__init__()
        self.n_freqs, self.in_dim, self.include_input = n_freqs, in_dim, include_input
        self.out_dim = in_dim * (int(include_input) + 2 * n_freqs)
        # Powers of two are exact in every float type, so 2^k (pi x) rounds only in pi x, at x's precision.
        self.register_buffer("powers", 2.0 ** torch.arange(n_freqs), persistent=False)

    def forward(self, x: Tensor) -> Tensor:
        scaled = ((torch.pi * x)[..., None, :] * self.powers[:, None]).flatten(-2)  # [..., L * D], k-major
        parts = [x] if self.include_input else []
        return torch.cat(parts + [torch.sin(scaled), torch.cos(scaled)], dim=-1)
