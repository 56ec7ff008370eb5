"""A set of posed images: what every dataset format is loaded into."""

from dataclasses import dataclass

from torch import Tensor


@dataclass
class Views:
    """Posed RGBA images of one split.

    rgba: [N, H, W, 4] float32 in [0, 1], straight (not premultiplied) alpha.
    c2w: [N, 4, 4] float32 camera-to-world matrices, OpenGL convention (see ``nerfexp.cameras``).
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
