import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from nerfexp.pixels import quantize
from nerfexp.scoring.metrics import SSIM_CROP, SSIM_WINDOW, psnr, ssim, unscorable


def test_psnr_of_a_known_error():
    target = torch.full((8, 8, 3), 100 / 255)
    image = torch.full((8, 8, 3), 110 / 255)  # error 10/255 everywhere: PSNR = 20 log10(25.5)
    assert math.isclose(psnr(image, target), 20 * math.log10(25.5), rel_tol=1e-9)


def test_psnr_quantizes_like_a_saved_png():
    target = torch.full((4, 4, 3), 0.5)
    assert psnr(target + 0.4 / 255, target) == math.inf  # rounds to the same 8-bit value
    assert torch.equal(quantize(torch.tensor([-1.0, 0.5 / 255 - 1e-6, 2.0])), torch.tensor([0.0, 0.0, 1.0]))


def test_ssim_identical_and_known_structure():
    rng = np.random.default_rng(0)
    image = torch.from_numpy(rng.random((32, 32, 3))).float()
    assert ssim(image, image) == pytest.approx(1.0)
    # A constant image against itself shifted by c: only the luminance term differs. With the
    # population statistics every window has mu_x = a, mu_y = a + c, sigma = 0, so
    # SSIM = (2 a (a + c) + C1) / (a^2 + (a + c)^2 + C1), C1 = (0.01)^2.
    a, c = 102 / 255, 51 / 255
    value = ssim(torch.full((32, 32, 3), a + c), torch.full((32, 32, 3), a))
    c1 = 0.01 ** 2
    assert value == pytest.approx((2 * a * (a + c) + c1) / (a * a + (a + c) ** 2 + c1), rel=1e-9)


def _reference_ssim(a: np.ndarray, b: np.ndarray) -> float:
    """SSIM as tf.image.ssim(max_val=1) defines it, written out: an 11-tap Gaussian of sigma 1.5,
    'valid' filtering, population (co)variances, K1 = 0.01, K2 = 0.03, mean over pixels and channels."""
    x = np.arange(11) - 5.0
    g = np.exp(-x ** 2 / (2 * 1.5 ** 2))
    g /= g.sum()

    def blur(img):  # separable valid convolution over rows then columns, per channel
        rows = np.stack([np.convolve(r, g, "valid") for r in img.reshape(img.shape[0], -1).T], 1)
        rows = rows.reshape(-1, img.shape[1], img.shape[2])
        return np.stack([[np.convolve(rows[i, :, c], g, "valid") for c in range(img.shape[2])]
                         for i in range(rows.shape[0])]).transpose(0, 2, 1)

    c1, c2 = 0.01 ** 2, 0.03 ** 2
    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b = blur(a * a) - mu_a ** 2, blur(b * b) - mu_b ** 2
    cov = blur(a * b) - mu_a * mu_b
    ssim_map = (2 * mu_a * mu_b + c1) * (2 * cov + c2) / ((mu_a ** 2 + mu_b ** 2 + c1) * (var_a + var_b + c2))
    return float(ssim_map.mean())


def test_ssim_matches_a_written_out_tensorflow_convention_reference():
    rng = np.random.default_rng(1)
    a = rng.random((40, 36, 3))
    b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1)
    qa, qb = (quantize(torch.from_numpy(x)) for x in (a, b))
    assert ssim(qa, qb) == pytest.approx(_reference_ssim(qa.numpy(), qb.numpy()), abs=1e-9)


def test_an_image_smaller_than_ssims_window_has_no_ssim_and_one_as_large_has():
    # the right half of a 12-pixel-wide test image (NeRF-W's protocol) is 6 wide: under the 11-pixel window
    assert math.isnan(ssim(torch.rand(12, 6, 3), torch.rand(12, 6, 3)))
    image = torch.rand(11, 11, 3)
    assert ssim(image, image) == pytest.approx(1.0)


@settings(max_examples=80, deadline=None)
@given(height=st.integers(1, 24), width=st.integers(1, 24), n=st.integers(1, 3), seed=st.integers(0, 2 ** 31),
       kept=st.sampled_from([None, 0.0, 0.01, 0.1, 1.0]))
def test_unscorable_says_exactly_which_images_psnr_or_ssim_leave_without_a_score(height, width, n, seed, kept):
    # independent truth: the scores themselves, NaN where they have none
    g = torch.Generator().manual_seed(seed)
    images, targets = torch.rand(2, n, height, width, 3, generator=g)
    mask = None if kept is None else torch.rand(n, height, width, generator=g) < kept  # [N, H, W]
    nan = [math.isnan(psnr(images[i], targets[i], None if mask is None else mask[i]))
           or math.isnan(ssim(images[i], targets[i], None if mask is None else mask[i])) for i in range(n)]
    problem = unscorable(height, width, mask)
    assert (problem is None) == (not any(nan))
    if problem is not None:
        assert problem[0] == nan.index(True)


def test_unscorable_names_why():
    assert unscorable(10, 40, None) == (0, "is 40x10 pixels, smaller than SSIM's 11x11 window")
    mask = torch.ones(3, 12, 12, dtype=torch.bool)
    mask[1] = False
    assert unscorable(12, 12, mask) == (1, "keeps no pixel (its mask)")
    mask[1] = True
    mask[2, SSIM_CROP:-SSIM_CROP, SSIM_CROP:-SSIM_CROP] = False  # only the border, which SSIM leaves out
    assert unscorable(12, 12, mask) == (2, "keeps no pixel more than 5 pixels from its edges, where SSIM is scored")
    assert unscorable(SSIM_WINDOW, SSIM_WINDOW, mask[:1, :SSIM_WINDOW, :SSIM_WINDOW]) is None
    mask[1] = False  # an earlier image without a scored pixel is named first, whatever the reason of a later one
    assert unscorable(12, 12, mask) == (1, "keeps no pixel (its mask)")
    mask[0, SSIM_CROP:-SSIM_CROP, SSIM_CROP:-SSIM_CROP] = False
    assert unscorable(12, 12, mask) == (0, "keeps no pixel more than 5 pixels from its edges, where SSIM is scored")
