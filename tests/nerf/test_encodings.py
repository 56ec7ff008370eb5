import math

import pytest
import torch

from nerfexp.nerf.encodings import IdentityEncoding, PositionalEncoding


def test_positional_encoding_values_by_hand():
    enc = PositionalEncoding(n_freqs=2)
    x = torch.tensor([[0.25, 0.5, -1.0]], dtype=torch.float64)
    out = enc.double()(x)[0]
    # layout: x (3) | sin(pi x), sin(2 pi x) (k-major, 3 each) | cos(pi x), cos(2 pi x)
    expected = [0.25, 0.5, -1.0,
                math.sin(math.pi / 4), 1.0, 0.0, 1.0, 0.0, 0.0,
                math.cos(math.pi / 4), 0.0, -1.0, 0.0, -1.0, 1.0]
    torch.testing.assert_close(out, torch.tensor(expected, dtype=torch.float64), atol=1e-12, rtol=0)


def test_paper_sizes():
    assert PositionalEncoding(10).out_dim == 63
    assert PositionalEncoding(4).out_dim == 27
    assert PositionalEncoding(10)(torch.zeros(5, 7, 3)).shape == (5, 7, 63)
    assert PositionalEncoding(3, include_input=False).out_dim == 18


def test_highest_frequency_is_2_to_the_L_minus_1():
    enc = PositionalEncoding(n_freqs=10).double()
    x = torch.tensor([[1.0 / 2 ** 10, 0.0, 0.0]], dtype=torch.float64)  # sin(2^9 pi x) = sin(pi / 2) = 1
    sines = enc(x)[0, 3:33].reshape(10, 3)
    assert math.isclose(sines[9, 0].item(), 1.0, abs_tol=1e-12)
    assert math.isclose(sines[0, 0].item(), math.sin(math.pi / 2 ** 10), abs_tol=1e-15)


def test_identity():
    x = torch.randn(4, 3)
    assert IdentityEncoding().out_dim == 3
    assert torch.equal(IdentityEncoding()(x), x)


def textbook_encoding_float64(x: torch.Tensor, n_freqs: int) -> torch.Tensor:
    """gamma(x) computed directly in float64 from the formula: the reference."""
    x = x.double()
    angles = (torch.pi * x[..., None, :] * 2.0 ** torch.arange(n_freqs, dtype=torch.float64)[:, None]).flatten(-2)
    return torch.cat([x, torch.sin(angles), torch.cos(angles)], -1)


@pytest.mark.parametrize("n_freqs", [10, 15, 20])
def test_float32_encoding_matches_float64_at_every_frequency(n_freqs):
    # Scene coordinates: cameras at radius 4 and far = 6 put samples within |x| < 10. The float32
    # encoding of a float32 input must match the float64 formula on that same input to ~1e-6 at every
    # frequency: its range reduction is exact, so only pi r (|r| < 2) and sin/cos round.
    x = (torch.rand(50_000, 3, generator=torch.Generator().manual_seed(0)) * 20 - 10).float()
    error = (PositionalEncoding(n_freqs)(x).double() - textbook_encoding_float64(x, n_freqs)).abs().max().item()
    assert error < 1e-6, error
    # The textbook float32 formula sin(2^k (pi x)) multiplies the rounding of pi x by 2^k: its error at the
    # top frequency is about 2^(L-1) pi |x| 2^-24 (0.002 at L = 10, 0.06 at L = 15, 1 at L = 20).
    naive_angles = ((torch.pi * x)[..., None, :] * 2.0 ** torch.arange(n_freqs)[:, None]).flatten(-2)
    naive = torch.cat([x, torch.sin(naive_angles), torch.cos(naive_angles)], -1)
    naive_error = (naive.double() - textbook_encoding_float64(x, n_freqs)).abs().max().item()
    bound = 2 ** (n_freqs - 1) * torch.pi * 10 * 2.0 ** -24
    assert 0.1 * min(bound, 1) < naive_error <= 2 * bound


def test_encoding_gradient_is_the_derivative_of_the_formula():
    # d/dx sin(2^k pi x) = 2^k pi cos(2^k pi x): the fmod reduction passes the gradient through unchanged
    x = torch.tensor([[0.3, -1.7, 2.9]], dtype=torch.float64, requires_grad=True)
    out = PositionalEncoding(6).double()(x)
    out[0, 3 + 5 * 3 + 1].backward()  # sin(2^5 pi x_1)
    expected = 2 ** 5 * math.pi * math.cos(2 ** 5 * math.pi * -1.7)
    assert math.isclose(x.grad[0, 1].item(), expected, rel_tol=1e-12)
    assert x.grad[0, 0] == 0 and x.grad[0, 2] == 0


def test_input_scale_moves_every_frequency_down():
    # gamma(x / 8), L = 4: sin(2^k pi x / 8), raw input x; at x = 2: sin(pi/4), sin(pi/2), sin(pi), sin(2 pi)
    enc = PositionalEncoding(n_freqs=4, in_dim=1, input_scale=0.125).double()
    out = enc(torch.tensor([[2.0]], dtype=torch.float64))[0]
    r = math.sqrt(0.5)
    expected = [2.0, r, 1.0, 0.0, 0.0, r, 0.0, -1.0, 1.0]
    torch.testing.assert_close(out, torch.tensor(expected, dtype=torch.float64), atol=1e-12, rtol=0)
