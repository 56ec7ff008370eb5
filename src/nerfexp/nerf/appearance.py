"""Per-image appearance (the ``appearance`` axis): NeRF in the Wild's learned code per training image (GLO,
Martin-Brualla et al. 2021), which the colour networks take beside the trunk's features, so that one scene
explains images whose exposure, white balance or lighting differ; and the two ways an image never trained on
gets a code (``PROTOCOLS``).

Conventions of this module: a ``code`` is one image's appearance vector [D]; ``codes`` are one per ray [B, D];
``views`` [B] (long) are the training images' indices the rays come from (``nerfexp.data.rays.RandomRays``).
"""

from collections.abc import Callable, Mapping
from typing import ClassVar

import torch
from torch import Tensor, nn

from nerfexp.domains import COUNT, Memory, Rule, choice
from nerfexp.nerf.frozen_fit import FrozenFit
from nerfexp.sizes import codes_bytes

# How a test image is scored (``results.json``'s ``test_protocol``): the whole image with the model's code for
# an unseen image (``AppearanceEmbedding.test_code``), or NeRF-W's: the image's own code fitted on its left half
# with the networks frozen (``CodeFit``), then its right half scored. Without appearance codes the second is
# the right half of the same render: there is no code to fit.
FULL_IMAGE = "full_image"
NERFW_RIGHT_HALF = "nerfw_right_half"
PROTOCOLS = (FULL_IMAGE, NERFW_RIGHT_HALF)
TEST_CODES = ("mean", "zero")  # the code of an image not trained on: the training codes' mean, or zero


def left_columns(width: int) -> int:
    """The columns [0, W // 2) of an image W wide are its left half, fitted on; [W // 2, W) its right half,
    scored (an odd middle column belongs to the right)."""
    return width // 2


class AppearanceEmbedding(nn.Module):
    """A learned code [dim] per training image, all zero at first (every image starts as the same appearance,
    and no random numbers are drawn, so that turning it on leaves the networks' initial weights' stream as it
    was). ``codes`` [N, dim] has no rows until ``set_views(N)`` (``NeRFModule.setup``: the data module's training
    views) or a checkpoint's rows are loaded: its size comes from the data, never from a setting.

    ``forward(views)`` -> codes [B, dim]: the rows of the batch's images, so that a step's gradient reaches those
    rows alone. ``test_code()`` [dim]: the code of an image not trained on, the codes' mean (nerfstudio's average
    appearance) or zero (``test_code`` argument).
    """

    DOMAINS: ClassVar[dict[str, Rule]] = {"dim": COUNT, "test_code": choice(*TEST_CODES)}

    @staticmethod
    def MEMORY_PER_VIEW(config: Mapping, views: int) -> list[Memory]:
        """A code per training view, trained."""
        return [(("dim",), f"training the appearance codes of {views} views of {config['dim']} numbers",
                 codes_bytes(views, config["dim"]))]

    def __init__(self, dim: int = 48, test_code: str = "mean"):
        super().__init__()
        if test_code not in TEST_CODES:
            raise ValueError(f"appearance.embedding.test_code: expected one of {', '.join(TEST_CODES)}, "
                             f"got {test_code!r}")
        self.dim = dim
        self.mode = test_code
        self.codes = nn.Parameter(torch.zeros(0, dim))
        self.register_load_state_dict_pre_hook(AppearanceEmbedding._size_from_checkpoint)

    @property
    def n_views(self) -> int:
        return self.codes.shape[0]

    def set_views(self, n_views: int) -> None:
        """One zero code for each of ``n_views`` training images; where the codes are sized already (a
        checkpoint's), ``n_views`` must be their number."""
        if n_views < 1:
            raise ValueError(f"appearance codes: expected at least one training view, got {n_views}")
        if self.n_views == 0:
            self.codes = nn.Parameter(self.codes.new_zeros(n_views, self.dim))
        elif self.n_views != n_views:
            raise ValueError(f"appearance codes: {self.n_views} codes (one per training view it was trained on), "
                             f"but the data has {n_views} training views")

    @staticmethod
    def _size_from_checkpoint(module: "AppearanceEmbedding", state_dict: dict, prefix: str, *args) -> None:
        """Before a checkpoint's weights are loaded into codes with no rows yet: as many rows as it has."""
        saved = state_dict.get(prefix + "codes")
        if saved is not None and module.n_views == 0 and saved.ndim == 2 and saved.shape[0] > 0:
            module.set_views(saved.shape[0])

    def forward(self, views: Tensor) -> Tensor:
        """views [B] (long) -> their codes [B, dim]."""
        return self.codes[views]

    def test_code(self) -> Tensor:
        """The code [dim] of an image not trained on: the training codes' mean, or zero (``test_code``)."""
        if self.mode == "zero" or self.n_views == 0:
            return self.codes.new_zeros(self.dim)
        return self.codes.detach().mean(0)


class CodeFit(FrozenFit):
    """NeRF-W's test-time fit of one image's code, the networks frozen (``FrozenFit``): ``steps`` steps of Adam at
    learning rate ``lr`` on the code alone, each on ``rays`` of the image's fitting pixels drawn with replacement
    from a generator seeded with the image's index (the same pixels whatever else ran before)."""

    @staticmethod
    def RAYS(config: Mapping) -> tuple[int, tuple[str, ...], str]:
        """A step renders ``rays`` rays, their outputs kept for the backward pass to the code."""
        return config["rays"], ("rays",), "a step of the test images' appearance fit"

    def __init__(self, steps: int = 64, lr: float = 0.05, rays: int = 256):
        super().__init__(steps, lr, rays)

    def __call__(self, loss: Callable[[Tensor, Tensor], Tensor], start: Tensor, n_pixels: int, seed: int,
                 progress: Callable[[int], None] | None = None) -> Tensor:
        """The code [D] fitted from ``start`` [D]: ``loss(pixels [R], code [D])`` is the scalar loss of the
        fitting pixels ``pixels`` (indices < ``n_pixels``) rendered with ``code`` (``fit_frozen``: only the code
        is differentiated, so no other tensor's gradient or value changes); ``progress(steps done)`` after each
        step, where given."""
        return self.fit(loss, start, n_pixels, seed, progress)
