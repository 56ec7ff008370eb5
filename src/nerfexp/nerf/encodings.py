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
    ``input_scale`` s encodes s p instead of p (the raw input stays p): every frequency moves down
    log2(1/s) octaves. s = 1 is the paper's; a power of two keeps the range reduction below exact.

    Exact range reduction: sin(2^k pi x) = sin(pi r) with r = fmod(2^k x, 2). Scaling by a power of two
    and ``fmod`` are exact in floating point, so the phase is rounded once, in pi r with |pi r| < 2 pi,
    and every frequency of the float32 input is computed to about 1e-6 (``tests/nerf/test_encodings.py``).
    The textbook ``sin(2^k (pi x))`` rounds pi x first and multiplies that rounding by 2^k, an error that
    grows with k (docs/numerics.md, ``benchmarks/encoding_precision.py``).

    >>> PositionalEncoding(n_freqs=1)(torch.tensor([[0.5, 0.0, 0.0]]))[0, 3:6]  # sin(pi x)
    tensor([1., 0., 0.])
    """

    def __init__(self, n_freqs: int, in_dim: int = 3, include_input: bool = True, input_scale: float = 1.0):
        super().__init__()
        self.n_freqs, self.in_dim, self.include_input = n_freqs, in_dim, include_input
        self.out_dim = in_dim * (int(include_input) + 2 * n_freqs)
        self.register_buffer("powers", input_scale * 2.0 ** torch.arange(n_freqs), persistent=False)

    def forward(self, x: Tensor) -> Tensor:
        """x [..., D] -> [..., out_dim]."""
        scaled = (x[..., None, :] * self.powers[:, None].to(x.dtype)).flatten(-2)  # s 2^k x: [..., L * D]
        phase = torch.pi * torch.fmod(scaled, 2)  # same sine and cosine, |phase| < 2 pi
        parts = [x] if self.include_input else []
        return torch.cat(parts + [torch.sin(phase), torch.cos(phase)], dim=-1)
