"""BARF's coarse-to-fine window on the positional encoding: the weights against their definition, the encoding
with the window off exactly the paper's, and the window opening with training's progress."""

import math

import pytest
import torch

from nerfexp.nerf.encodings import PositionalEncoding, coarse_to_fine_window


@pytest.mark.parametrize("fraction", [0.0, 0.05, 0.2, 0.37, 0.5, 0.93, 1.0])
def test_the_window_follows_its_definition(fraction):
    L = 10
    alpha = fraction * L
    expected = [(1 - math.cos(math.pi * min(max(alpha - k, 0.0), 1.0))) / 2 for k in range(L)]
    assert torch.allclose(coarse_to_fine_window(L, fraction), torch.tensor(expected), atol=1e-7)


def test_without_a_window_the_encoding_is_the_papers():
    x = torch.randn(50, 3, generator=torch.Generator().manual_seed(0))
    plain, off = PositionalEncoding(10), PositionalEncoding(10, coarse_to_fine=0.0)
    off.set_progress(0.3)  # nothing to change
    assert torch.equal(plain(x), off(x))
    assert "window" not in dict(off.named_buffers())


def test_the_window_opens_with_progress_and_is_saved():
    x = torch.randn(50, 3, generator=torch.Generator().manual_seed(0))
    encoding, plain = PositionalEncoding(4, coarse_to_fine=0.5), PositionalEncoding(4)
    assert torch.equal(encoding(x)[:, :3], x)  # the raw input is never weighted
    assert torch.equal(encoding(x)[:, 3:], torch.zeros(50, 24))  # at the start every frequency is closed
    encoding.set_progress(0.125 * 1.5)  # alpha = 4 x 0.1875 / 0.5 = 1.5: k = 0 open, k = 1 half
    sines, plain_sines = encoding(x)[:, 3:15].reshape(50, 4, 3), plain(x)[:, 3:15].reshape(50, 4, 3)
    assert torch.equal(sines[:, 0], plain_sines[:, 0])
    assert torch.allclose(sines[:, 1], 0.5 * plain_sines[:, 1], atol=1e-7)
    assert torch.equal(sines[:, 2:], torch.zeros(50, 2, 3))
    encoding.set_progress(0.7)  # past the fraction: all open
    assert torch.equal(encoding(x), plain(x))
    assert torch.equal(encoding.state_dict()["window"], torch.ones(4))
