"""Image quality as NeRF papers report it: on 8-bit images, SSIM with TensorFlow's conventions; where a mask
says which pixels count (a capture's masks, ``nerfexp.data.views.Views.mask``), over those pixels only."""

import numpy as np
import torch
from skimage.metrics import structural_similarity
from torch import Tensor

from nerfexp.pixels import quantize

SSIM_SIGMA = 1.5  # tf.image.ssim's Gaussian window: sigma 1.5, 11 taps (skimage: radius int(3.5 sigma + 0.5) = 5)
SSIM_CROP = 5  # the border skimage leaves out of its mean: (11 - 1) / 2 pixels on each side
SSIM_WINDOW = 2 * SSIM_CROP + 1  # the window's side: an image narrower or shorter than it has no SSIM


def psnr(image: Tensor, target: Tensor, mask: Tensor | None = None) -> float:
    """PSNR in dB of [H, W, 3] images in [0, 1], both quantized to 8 bits: -10 log10(MSE), the MSE over the
    pixels ``mask`` [H, W] keeps (None: all)."""
    squared = (quantize(image.double()) - quantize(target.double())) ** 2
    mse = (squared.mean() if mask is None else squared[mask.to(squared.device)].mean()).item()
    return float("inf") if mse == 0 else -10 * np.log10(mse)


def ssim(image: Tensor, target: Tensor, mask: Tensor | None = None) -> float:
    """SSIM of [H, W, 3] images in [0, 1] after 8-bit quantization, as ``tf.image.ssim(max_val=1)``:
    an 11-tap Gaussian window of sigma 1.5, K1 0.01, K2 0.03, population covariance. With ``mask`` [H, W]:
    the mean of the SSIM map over the pixels the mask keeps, within the border skimage's own mean leaves
    out (``SSIM_CROP``); an all-true mask gives skimage's score. An image smaller than the window
    (``SSIM_WINDOW``) on a side has none: NaN (the right half of a 12-pixel test image, for NeRF-W's protocol)."""
    if min(image.shape[:2]) < SSIM_WINDOW:
        return float("nan")
    a = quantize(image.double()).cpu().numpy()
    b = quantize(target.double()).cpu().numpy()
    score, full = structural_similarity(a, b, data_range=1.0, channel_axis=-1, gaussian_weights=True,
                                        sigma=SSIM_SIGMA, use_sample_covariance=False, full=True)
    if mask is None:
        return float(score)
    inner = (slice(SSIM_CROP, -SSIM_CROP), slice(SSIM_CROP, -SSIM_CROP))
    kept = mask.cpu().numpy()[inner]
    return float(full[inner][kept].mean()) if kept.any() else float("nan")


def unscorable(height: int, width: int, mask: Tensor | None) -> tuple[int, str] | None:
    """The first of N images ``height`` x ``width`` that ``psnr`` or ``ssim`` leaves without a score (NaN), and
    why, or None where every image has both: images smaller than SSIM's window (``SSIM_WINDOW``) on a side; an
    image whose ``mask`` [N, H, W] (None: every pixel counts) keeps no pixel; one that keeps none farther than
    ``SSIM_CROP`` pixels from its edges, where SSIM's map is averaged."""
    if min(height, width) < SSIM_WINDOW:
        return 0, f"is {width}x{height} pixels, smaller than SSIM's {SSIM_WINDOW}x{SSIM_WINDOW} window"
    if mask is None:
        return None
    kept_none = ~mask.flatten(1).any(1)  # [N]
    kept_none_inside = ~mask[:, SSIM_CROP:-SSIM_CROP, SSIM_CROP:-SSIM_CROP].flatten(1).any(1)  # [N], kept_none's too
    if not kept_none_inside.any():
        return None
    first = int(torch.nonzero(kept_none_inside)[0])
    if kept_none[first]:
        return first, "keeps no pixel (its mask)"
    return first, f"keeps no pixel more than {SSIM_CROP} pixels from its edges, where SSIM is scored"
