"""Image quality as NeRF papers report it: on 8-bit images, SSIM with TensorFlow's conventions."""

import numpy as np
import torch
from skimage.metrics import structural_similarity
from torch import Tensor

from nerfexp.pixels import quantize


def psnr(image: Tensor, target: Tensor) -> float:
    """PSNR in dB of [H, W, 3] images in [0, 1], both quantized to 8 bits: -10 log10(MSE)."""
    mse = torch.mean((quantize(image.double()) - quantize(target.double())) ** 2).item()
    return float("inf") if mse == 0 else -10 * np.log10(mse)


def ssim(image: Tensor, target: Tensor) -> float:
    """SSIM of [H, W, 3] images in [0, 1] after 8-bit quantization, as ``tf.image.ssim(max_val=1)``:
    an 11-tap Gaussian window of sigma 1.5, K1 0.01, K2 0.03, population covariance."""
    a = quantize(image.double()).cpu().numpy()
    b = quantize(target.double()).cpu().numpy()
    return float(structural_similarity(a, b, data_range=1.0, channel_axis=-1, gaussian_weights=True,
                                       sigma=1.5, use_sample_covariance=False))
