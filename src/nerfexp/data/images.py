"""Image files as the dataset formats read them: 8-bit RGBA tensors, shrunk by area averaging."""

import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import Tensor

from nerfexp.errors import DatasetError


def read_image(path: Path, source: str) -> Tensor:
    """An image file as 8-bit RGBA [H, W, 4]; images without alpha get alpha 255. ``source`` names what
    pointed to the file, for the error when it is missing."""
    if not path.is_file():
        raise DatasetError(f"image {path} does not exist (named by {source})")
    try:
        with Image.open(path) as image:
            rgba = np.asarray(image.convert("RGBA"))
    except OSError as error:
        raise DatasetError(f"{path}: cannot read the image ({error})") from None
    return torch.from_numpy(rgba.copy())


def downscale_rgba(rgba: Tensor, factor: int) -> Tensor:
    """Area-average straight-alpha images [N, H, W, 4] down to [N, H // factor, W // factor, 4].

    Colour is averaged premultiplied by alpha (so transparent pixels' colours do not bleed into
    edges), then divided by the averaged alpha where it is positive. Each output pixel averages
    the input pixels under its footprint (adaptive average pooling): when ``factor`` divides H
    and W these are exact factor x factor blocks, otherwise the whole image is still covered, so
    a focal length computed from the new width stays right.
    """
    N, H, W, _ = rgba.shape  # views, rows, columns
    if H // factor < 1 or W // factor < 1:
        raise DatasetError(f"downscale {factor} is larger than the images ({W}x{H})")
    rgb, alpha = rgba[..., :3], rgba[..., 3:]
    premultiplied = torch.cat([rgb * alpha, alpha], -1).permute(0, 3, 1, 2)  # [N, 4, H, W]
    pooled = F.adaptive_avg_pool2d(premultiplied, (H // factor, W // factor)).permute(0, 2, 3, 1)
    alpha = pooled[..., 3:]
    rgb = torch.where(alpha > 0, pooled[..., :3] / alpha.clamp_min(torch.finfo(alpha.dtype).tiny), 0.0)
    return torch.cat([rgb.clamp(0, 1), alpha], -1)


def fit_factor(side: int, max_side: int | None) -> int:
    """The smallest integer factor that shrinks an image's longer ``side`` to at most ``max_side`` pixels
    (1: it fits already, or ``max_side`` is None)."""
    return math.ceil(side / max_side) if max_side is not None and side > max_side else 1
