"""A set of posed images: what every dataset format is loaded into."""

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from nerfexp.errors import DatasetError
from nerfexp.geometry.lenses import Intrinsics

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")  # what a folder of photographs may hold


@dataclass
class Views:
    """Posed RGBA images of one split.

    rgba: [N, H, W, 4] float32 in [0, 1], straight (not premultiplied) alpha.
    c2w: [N, 4, 4] float32 camera-to-world matrices, OpenGL convention (see ``nerfexp.geometry.cameras``).
    intrinsics: [N] each view's lens, float64: focal lengths, principal point and distortion in the images'
        pixels (``nerfexp.geometry.lenses``).
    mask: [N, H, W] bool, the pixels that count (in the loss and the scores), or None: all of them.
    """

    rgba: Tensor
    c2w: Tensor
    intrinsics: Intrinsics
    mask: Tensor | None = None

    @property
    def height(self) -> int:
        return self.rgba.shape[1]

    @property
    def width(self) -> int:
        return self.rgba.shape[2]

    def __len__(self) -> int:
        return self.rgba.shape[0]

    def subset(self, index: Tensor) -> "Views":
        """The views ``index`` [K] (indices or a mask), in that order."""
        return Views(rgba=self.rgba[index], c2w=self.c2w[index], intrinsics=self.intrinsics[index],
                     mask=None if self.mask is None else self.mask[index])

    def resized(self, rgba: Tensor) -> "Views":
        """These views with their images replaced by ``rgba`` [N, H', W', 4], the same images resampled over
        the same extent (``downscale_rgba``): the lenses follow (``Intrinsics.resized``), and a pixel of the
        mask counts where every pixel under it counted (``shrink_mask``)."""
        size = tuple(rgba.shape[1:3])
        intrinsics = self.intrinsics.resized((self.height, self.width), size)
        return Views(rgba=rgba, c2w=self.c2w, intrinsics=intrinsics,
                     mask=None if self.mask is None else shrink_mask(self.mask, size))

    def rgb_on(self, background: Tensor) -> Tensor:
        """Colours composited over ``background`` [3]: [N, H, W, 3]."""
        rgb, alpha = self.rgba[..., :3], self.rgba[..., 3:]
        return rgb * alpha + background * (1 - alpha)


def shrink_mask(mask: Tensor, size: tuple[int, int]) -> Tensor:
    """Masks [N, H, W] bool shrunk to ``size`` (H', W') over the same extent by adaptive average pooling, as
    images are (``nerfexp.data.images.downscale_rgba``): a pixel counts where every pixel under it counted
    (a mean of ones is exactly 1)."""
    pooled = F.adaptive_avg_pool2d(mask[:, None].float(), size)[:, 0]  # [N, H', W']
    return pooled == 1


def holdout_split(n: int, holdout: int, n_val: int, n_train: int | None = None) -> dict[str, Tensor]:
    """Image indices per split of ``n`` images: test every ``holdout``-th (i % holdout == 0, the LLFF
    convention), train the first ``n_train`` of the rest (None: all; more than there are is a DatasetError),
    val the first ``n_val`` test ones (all of them where there are fewer)."""
    index = torch.arange(n)
    train, test = index[index % holdout != 0], index[index % holdout == 0]
    if n_train is not None and n_train > len(train):  # a cut would leave fewer views than the run records
        raise DatasetError(f"data.n_train={n_train}: only {len(train)} of the {n} images are training images "
                           f"(every {holdout}th is held out for testing)")
    return {"train": train[:n_train], "val": test[:n_val], "test": test}
