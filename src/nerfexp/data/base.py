"""The ``Scene``: what every dataset format provides (``data`` in the config builds one), each member
the rest of nerfexp uses spelled out, with a default where a format may leave it out."""

import abc
from collections.abc import Mapping
from typing import ClassVar

from torch import Tensor

from nerfexp.data.views import Views
from nerfexp.domains import BOX, COUNT, FAR, NEAR, PATH, RAW_LIMIT, Rule, choice, optional, real
from nerfexp.errors import ConfigError
from nerfexp.geometry.boxes import frustum_aabb, parse_aabb
from nerfexp.nerf.backgrounds import BACKGROUNDS


class Scene(abc.ABC):
    """A dataset: posed views per split, and how the model sees the scene.

    Members every format has (dataclass fields of the formats, keys of their configs):
        background: the name of the colour where rays absorb nothing (``nerfexp.nerf.backgrounds``).
        near, far: the ray parameter's bounds (None where the format finds them: ``ray_bounds``).
        aabb: the occupancy grid's box from the config, ``[[x0, y0, z0], [x1, y1, z1]]``, or None.
        density_noise_std: the std of the N(0, std^2) noise the field adds to raw densities in training on
            such a scene (the paper's 1 for real forward-facing captures, 0 for synthetic ones); the field's
            config reads it (``${data.density_noise_std}``), so the scene's format chooses it and the
            command line still can.
    Methods with a default: ``split_rule``, ``bounds_rule``, ``bounding_box``, ``ray_bounds``, ``depth_bounds``, ``model_rays``.
    """

    # the domains of the arguments every format shares (nerfexp.domains; a format adds its own)
    DOMAINS: ClassVar[dict[str, Rule]] = {
        "root": PATH,
        "max_side": optional(COUNT, "never shrink"),
        "n_train": optional(COUNT, "all"),
        "n_val": COUNT,
        "near": optional(NEAR, "from the scene"),
        "far": optional(FAR, "from the scene"),
        "background": choice(*BACKGROUNDS),
        "aabb": BOX,
        "density_noise_std": real(0, RAW_LIMIT),
    }
    # its settings that only other components read (their SCENE_FIELDS): the box, of the grids
    SERVES: ClassVar[tuple[str, ...]] = ("aabb",)

    @staticmethod
    def TRAINING_VIEWS(config: Mapping) -> tuple[int, tuple[str, ...]]:
        """The training views (at least one: null, all of the scene's) and the arguments that set them."""
        return config.get("n_train") or 1, ("n_train",) if "n_train" in config else ()

    background: str
    near: float | None
    far: float | None
    aabb: list | None = None
    density_noise_std: float = 0.0

    @abc.abstractmethod
    def views(self, split: str) -> Views:
        """The posed images of ``split``: "train", "val" or "test"."""

    def split_rule(self) -> str | None:
        """How the views were split into train, val and test, where a rule (not the dataset's own files)
        or a choice between rules made them; results.json records it as ``split``. None: the format's own
        splits."""
        return None

    def bounds_rule(self) -> str | None:
        """Where the ray bounds ``ray_bounds()`` came from, where the format found them (not both configured);
        results.json records it as ``bounds``. None: the configured values."""
        return None

    def bounding_box(self) -> Tensor | None:
        """The box [2, 3] that holds the scene's content, where the format knows it; None: bound it from
        the training cameras (``box``)."""
        return None

    def ray_bounds(self) -> tuple[float, float]:
        """``(near, far)``, the bounds of the rays' parameter t: the configured ones."""
        return self.near, self.far

    def depth_bounds(self) -> Tensor | None:
        """[N, 2]: each view's near and far depth, where the format records them (LLFF); else None."""
        return None

    def model_rays(self, origins: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        """The rays the model renders, made from world rays [..., 3]: the world rays themselves, or (LLFF)
        NDC rays."""
        return origins, directions

    def box(self, train_views: Views | None, near: float, far: float) -> Tensor:
        """The occupancy grid's box [2, 3], first match wins: ``aabb`` from the config; the scene's own
        ``bounding_box()``; else the box of everything the training cameras ``train_views`` see between
        ``near`` and ``far`` (``frustum_aabb``)."""
        if self.aabb is not None:
            return parse_aabb(self.aabb)
        own = self.bounding_box()
        if own is not None:
            return own
        if train_views is None:
            raise ConfigError("the scene has no bounding box and no training views to bound: set data.aabb")
        return frustum_aabb(train_views.c2w, train_views.intrinsics, train_views.height, train_views.width, near, far)
