"""Image files as the dataset formats read them: 8-bit RGBA tensors, shrunk by area averaging."""

import io
import math
import struct
import warnings
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import Tensor

from nerfexp.data.views import is_named_file
from nerfexp.errors import DatasetError
from nerfexp.reading import UnreadableFile, read_bytes

MAX_PIXELS = Image.MAX_IMAGE_PIXELS  # Pillow's limit (about 89 million): larger images are refused, not decoded
# the largest file such an image takes: uncompressed at 16 bits per channel with alpha, and its headers
MAX_FILE_BYTES = 8 * MAX_PIXELS + (1 << 20)


def to_rgba8(image: Image.Image) -> np.ndarray:
    """8-bit RGBA [H, W, 4] of a decoded image; 16-bit greyscale (Pillow's modes I;16 and I) is scaled
    from [0, 65535] (Pillow's own conversion would clip it to [0, 255])."""
    if image.mode.startswith("I"):
        grey = np.round(np.asarray(image, dtype=np.float64) / 257).clip(0, 255).astype(np.uint8)
        return np.dstack([grey, grey, grey, np.full_like(grey, 255)])
    return np.asarray(image.convert("RGBA"))


def read_image(path: Path, source: str) -> Tensor:
    """An image file as 8-bit RGBA [H, W, 4]; images without alpha get alpha 255. ``source`` names what
    pointed to the file, for the error when it is missing. The file is first checked with Pillow's
    ``verify`` (for PNG: every chunk's CRC-32, the image data's too, which decoding alone skips, so a
    flipped byte would otherwise decode to wrong pixels); a damaged file and an image of more than
    ``MAX_PIXELS`` pixels, or a file larger than such an image's (``MAX_FILE_BYTES``), are DatasetErrors,
    never decoded."""
    if not is_named_file(path, source):
        raise DatasetError(f"image {path} does not exist (named by {source})")
    try:
        data = read_bytes(path, MAX_FILE_BYTES)  # bounded: a dataset from others
    except UnreadableFile as error:
        raise DatasetError(str(error)) from None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            with Image.open(io.BytesIO(data)) as image:
                image.verify()
            with Image.open(io.BytesIO(data)) as image:  # verify leaves an image that cannot be decoded
                rgba = to_rgba8(image)
    except (Image.DecompressionBombError, Image.DecompressionBombWarning):
        raise DatasetError(f"{path}: more than {MAX_PIXELS} pixels, which nerfexp does not decode (a "
                           "decompression bomb, or an image to shrink before use)") from None
    except (OSError, ValueError, SyntaxError, struct.error) as error:  # Pillow's errors for damaged files
        raise DatasetError(f"{path}: a damaged or unreadable image file ({error})") from None
    return torch.from_numpy(rgba.copy())


def image_size(path: Path, source: str) -> tuple[int, int]:
    """(height, width) of an image file from its header alone (nothing is decoded); a missing or unreadable
    file is a DatasetError naming it (``source``: what pointed to the file)."""
    if not is_named_file(path, source):
        raise DatasetError(f"image {path} does not exist (named by {source})")
    try:
        with Image.open(path) as image:
            width, height = image.size
    except (OSError, ValueError, SyntaxError, struct.error) as error:
        raise DatasetError(f"{path}: a damaged or unreadable image file ({error})") from None
    return height, width


def has_alpha(path: Path) -> bool:
    """Whether the image file ``path`` carries transparency: an alpha channel (RGBA, LA, ...) or a
    transparent colour (PNG's ``tRNS``); ``read_image`` gives every other image alpha 255 (opaque). Reads
    the file's header only: call it on a file ``read_image`` has read."""
    with Image.open(path) as image:
        return "A" in image.getbands() or "transparency" in image.info


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
