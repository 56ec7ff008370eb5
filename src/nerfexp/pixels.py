"""8-bit pixels: images in [0, 1] rounded as an 8-bit PNG stores them, and PNG files of them."""

import io

import numpy as np
import torch
from PIL import Image
from torch import Tensor


def levels(image: Tensor) -> Tensor:
    """The 8-bit levels of values in [0, 1], any shape, in ``image``'s dtype: round(clamp(x) * 255), whole numbers
    in [0, 255] (exact in any float dtype)."""
    return torch.round(image.clamp(0, 1) * 255)


def quantize(image: Tensor) -> Tensor:
    """The image as an 8-bit PNG would store it, back in [0, 1]: round(clamp(x) * 255) / 255."""
    return levels(image) / 255


def to_uint8(image: Tensor) -> np.ndarray:
    """8-bit pixels (uint8, on the host) of values in [0, 1], any shape: round(clamp(x) * 255), as ``quantize``."""
    return levels(image).to(torch.uint8).cpu().numpy()


def png_bytes(pixels: np.ndarray) -> bytes:
    """PNG file contents of 8-bit pixels [H, W] (grey), [H, W, 3] (RGB) or [H, W, 4] (RGBA)."""
    buffer = io.BytesIO()
    Image.fromarray(pixels).save(buffer, format="PNG")
    return buffer.getvalue()


def depth_image(depth: Tensor, opacity: Tensor, near: float, far: float) -> Tensor:
    """Depth [H, W] as a grey image, near white and far black, faded by opacity [H, W] so that
    empty space (whose depth is the mean of vanishing weights) is black: [H, W] in [0, 1]."""
    return ((far - depth) / (far - near)).clamp(0, 1) * opacity.clamp(0, 1)
