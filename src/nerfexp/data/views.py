"""A set of posed images: what every dataset format is loaded into."""

from dataclasses import dataclass

import torch
from torch import Tensor

from nerfexp.errors import DatasetError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")  # what a folder of photographs may hold


@dataclass
class Views:
    """Posed RGBA images of one split.

    rgba: [N, H, W, 4] float32 in [0, 1], straight (not premultiplied) alpha.
    c2w: [N, 4, 4] float32 camera-to-world matrices, OpenGL convention (see ``nerfexp.geometry.cameras``).
    focal: focal length in pixels, shared by all views.
    """

    rgba: Tensor
    c2w: Tensor
    focal: float

    @property
    def height(self) -> int:
        return self.rgba.shape[1]

    @property
    def width(self) -> int:
        return self.rgba.shape[2]

    def __len__(self) -> int:
        return self.rgba.shape[0]

    def rgb_on(self, background: Tensor) -> Tensor:
        """Colours composited over ``background`` [3]: [N, H, W, 3]."""
        rgb, alpha = self.rgba[..., :3], self.rgba[..., 3:]
        return rgb * alpha + background * (1 - alpha)


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
