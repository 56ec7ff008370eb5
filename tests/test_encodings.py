import math

import torch

from nerfexp.encodings import IdentityEncoding, PositionalEncoding


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
