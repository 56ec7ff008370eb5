"""Input encodings for the field: each an ``Encoding``, mapping [..., in_dim] to [..., out_dim] and reporting
``out_dim``: the identity and the positional encoding here; the multiresolution hash grid, an ``Encoding`` too, in
``nerfexp.nerf.hashgrid``."""

import math
from typing import ClassVar

import torch
from torch import Tensor, nn

from nerfexp.domains import (
    BOOLEAN,
    FLOAT32_TOP_OCTAVE,
    FRACTION,
    NONNEGATIVE_COUNT,
    Applies,
    Consistent,
    Rule,
    real,
)

# gamma(s x): a scale above 2^18 puts even the lowest frequency past float32's (and with n_freqs,
# PositionalEncoding.CONSISTENT)
INPUT_SCALE = real(0, 2.0 ** FLOAT32_TOP_OCTAVE, above=True)


class Encoding(nn.Module):
    """The encoding axis's component: maps [..., in_dim] to [..., out_dim]; the field is built from ``out_dim``.

    ``parameter_groups`` names the encoding's own optimizer parameter groups, {name: {"params": [...],
    option: value}} (nerfstudio's ``get_param_groups``; ``NeRFModule.parameter_groups`` merges them by name
    across the networks' copies); by default none, and its parameters, if any, train with the networks'.
    ``sparse_gradients``: whether its parameters get sparse gradients (``NeRFModule.on_fit_start`` turns them
    dense where several processes train). ``DOMAINS`` and ``APPLIES`` declare its constructor's settings
    (``nerfexp.domains``).
    """

    DOMAINS: ClassVar[dict[str, Rule]] = {}
    APPLIES: ClassVar[dict[str, Applies]] = {}
    in_dim: int
    out_dim: int
    sparse_gradients: bool = False

    def parameter_groups(self) -> dict[str, dict]:
        return {}

    def kernels(self) -> tuple[str, ...]:
        """The fused kernels (``nerfexp.kernels``) its training will run where its parameters now are, so that a
        run builds them before its training clock starts; by default none."""
        return ()

    def set_progress(self, progress: float) -> None:
        """Told before each training step how far training is, ``progress`` = step / steps in [0, 1): for an
        encoding that changes over training (BARF's coarse-to-fine window); by default nothing."""


class IdentityEncoding(Encoding):
    """Raw coordinates, unchanged: the "No Pos. Encoding" ablation."""

    def __init__(self, in_dim: int = 3):
        super().__init__()
        self.in_dim = in_dim
        self.out_dim = in_dim

    def forward(self, x: Tensor) -> Tensor:
        return x


class PositionalEncoding(Encoding):
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
    grows with k (docs/numerics.md, ``benchmarks/accuracy/encoding_precision.py``).

    ``coarse_to_fine`` f > 0: BARF's window (Lin et al. 2021), for camera refinement: frequency k's sines and
    cosines weighted by w_k = (1 - cos(pi clamp(alpha - k, 0, 1))) / 2, alpha = L min(progress / f, 1) rising
    over the first fraction f of training (``set_progress``), so that the low frequencies align the cameras
    before the high ones fit detail; the raw input is never weighted. The window is a buffer, saved in
    checkpoints. 0: no window, the paper's encoding, computed exactly as without it.

    >>> PositionalEncoding(n_freqs=1)(torch.tensor([[0.5, 0.0, 0.0]]))[0, 3:6]  # sin(pi x)
    tensor([1., 0., 0.])
    """

    DOMAINS = {
        "n_freqs": NONNEGATIVE_COUNT,  # and the float32 limit (CONSISTENT)
        "input_scale": INPUT_SCALE,
        "include_input": BOOLEAN,
        "coarse_to_fine": FRACTION,
    }
    CONSISTENT: ClassVar[dict[tuple[str, ...], Consistent]] = {
        ("n_freqs", "input_scale"): lambda config: resolved_frequencies(config.get("n_freqs"),
                                                                        config.get("input_scale", 1.0)),
    }

    def __init__(self, n_freqs: int, in_dim: int = 3, include_input: bool = True, input_scale: float = 1.0,
                 coarse_to_fine: float = 0.0):
        super().__init__()
        self.n_freqs, self.in_dim, self.include_input = n_freqs, in_dim, include_input
        self.out_dim = in_dim * (int(include_input) + 2 * n_freqs)
        self.register_buffer("powers", input_scale * 2.0 ** torch.arange(n_freqs), persistent=False)
        self.coarse_to_fine = coarse_to_fine
        if coarse_to_fine > 0:
            self.register_buffer("window", coarse_to_fine_window(n_freqs, 0.0))

    def forward(self, x: Tensor) -> Tensor:
        """x [..., D] -> [..., out_dim]."""
        scaled = (x[..., None, :] * self.powers[:, None].to(x.dtype)).flatten(-2)  # s 2^k x: [..., L * D]
        phase = torch.pi * torch.fmod(scaled, 2)  # same sine and cosine, |phase| < 2 pi
        parts = [x] if self.include_input else []
        if self.coarse_to_fine > 0:
            weights = self.window.to(x.dtype).repeat_interleave(x.shape[-1])  # [L * D], frequency-major
            return torch.cat(parts + [torch.sin(phase) * weights, torch.cos(phase) * weights], dim=-1)
        return torch.cat(parts + [torch.sin(phase), torch.cos(phase)], dim=-1)

    def set_progress(self, progress: float) -> None:
        if self.coarse_to_fine > 0:
            self.window.copy_(coarse_to_fine_window(self.n_freqs, min(progress / self.coarse_to_fine, 1.0)))


def resolved_frequencies(n_freqs: int, input_scale: float) -> str | None:
    """What is expected of ``n_freqs`` frequencies of positions scaled by ``input_scale`` where the top one is
    beyond what float32 positions resolve, else None.

    The limit comes from ``benchmarks/accuracy/encoding_precision.py`` (docs/numerics.md): for points of a scene within
    |x| < 10 held in float32, features of frequency 2^k pi with k > ``FLOAT32_TOP_OCTAVE`` are noise. It applies
    to the frequencies the encoding sees, so an ``input_scale`` below 1 (gamma(s x)) allows more of them.

    >>> resolved_frequencies(20, 1.0)[:41]  # 2^19 pi is past the limit: 2^0 pi .. 2^18 pi are 19
    'at most 19 frequencies with input_scale 1'
    >>> resolved_frequencies(22, 0.125) is None  # 2^21 pi / 8 = 2^18 pi
    True
    """
    top = n_freqs - 1 + math.log2(input_scale)  # the octave of the highest frequency the encoding sees
    if n_freqs == 0 or top <= FLOAT32_TOP_OCTAVE:
        return None
    most = FLOAT32_TOP_OCTAVE + 1 - math.log2(input_scale)  # >= 1: its domain keeps the scale <= 2^18
    return (f"at most {math.floor(most)} frequencies with input_scale {input_scale:g}: frequencies above "
            f"2^{FLOAT32_TOP_OCTAVE} pi are noise for float32 positions (docs/numerics.md)")


def coarse_to_fine_window(n_freqs: int, fraction: float) -> Tensor:
    """BARF's weights [L] of frequencies k = 0..L-1 once alpha = ``fraction`` x L:
    w_k = (1 - cos(pi clamp(alpha - k, 0, 1))) / 2; 0 for every k at alpha = 0, 1 for every k at alpha = L.

    >>> coarse_to_fine_window(4, 0.375)  # alpha = 1.5: k = 0 open, k = 1 half, the rest closed
    tensor([1.0000, 0.5000, 0.0000, 0.0000])
    """
    alpha = fraction * n_freqs
    ramp = (alpha - torch.arange(n_freqs, dtype=torch.float64)).clamp(0, 1)
    return ((1 - torch.cos(torch.pi * ramp)) / 2).float()
