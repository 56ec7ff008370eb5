"""The ``Scene``: what every dataset format provides (``data`` in the config builds one), each member
the rest of nerfexp uses spelled out, with a default where a format may leave it out; and the ``FolderScene``, a
scene read from a folder: the one ``data.root`` names, or the cached one a catalogue's name stands for."""

import abc
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

from torch import Tensor

from nerfexp.data.catalog import SCENE_NAME, Entry, find_entry, scene_problem
from nerfexp.data.scene_cache import cached_folder, data_cache, fetch_scene, scene_record
from nerfexp.data.views import Views
from nerfexp.domains import BOX, COUNT, FAR, NEAR, PATH, RAW_LIMIT, Applies, Consistent, Rule, choice, optional, real
from nerfexp.downloads import MIRROR
from nerfexp.errors import ConfigError
from nerfexp.geometry.boxes import frustum_aabb, parse_aabb
from nerfexp.nerf.backgrounds import BACKGROUNDS


@dataclass(kw_only=True)
class Scene(abc.ABC):
    """A dataset: posed views per split, and how the model sees the scene.

    Members every format has, its dataclass fields here (keys of every format's config, keyword arguments: a format
    declares one again only to change its default):
        n_train: the training views, the first n_train of the format's (None: all of them).
        n_val: the validation views.
        background: the name of the colour where rays absorb nothing (``nerfexp.nerf.backgrounds``).
        near, far: the ray parameter's bounds (None where the format finds them: ``ray_bounds``).
        aabb: the occupancy grid's box from the config, ``[[x0, y0, z0], [x1, y1, z1]]``, or None (``box``).
        density_noise_std: the std of the N(0, std^2) noise the field adds to raw densities in training on
            such a scene (the paper's 1 for real forward-facing captures, 0 for synthetic ones); the field's
            config reads it (``${data.density_noise_std}``), so the scene's format chooses it and the
            command line still can.
    Methods with a default: ``fetch``, ``source``, ``frames_left_out``, ``split_rule``, ``bounds_rule``,
    ``bounding_box``, ``ray_bounds``, ``depth_bounds``, ``model_rays``.
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

    n_train: int | None = None
    n_val: int = 2
    background: str = "white"
    near: float | None = None
    far: float | None = None
    aabb: list | None = None
    density_noise_std: float = 0.0

    @abc.abstractmethod
    def views(self, split: str) -> Views:
        """The posed images of ``split``: "train", "val" or "test"."""

    def fetch(self) -> None:
        """Make the scene's files present before it is read, where they come from elsewhere (a scene by name,
        downloaded: ``FolderScene``); training calls it, the commands that read a run back never do."""

    def source(self) -> dict | None:
        """Where the scene's files came from, where they were fetched (``FolderScene``: its name, the archive's
        SHA-256 and how that digest was established); results.json records it as ``scene``. None: not fetched."""
        return None

    def frames_left_out(self) -> list[str] | None:
        """The frames the scene's files list whose images do not exist and which were left out (where the format
        leaves such frames out at all); results.json records them as ``frames_left_out``. None: none left out."""
        return None

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


def folder_given(config: Mapping) -> str | None:
    """Why a scene's name does nothing in a scene's ``config``: a folder given, which is read."""
    if config.get("root") is not None:
        return f"data.root={config['root']} (the folder given is read; data.scene names none then)"
    return None


def folder_unnamed(config: Mapping) -> str | None:
    """Why the settings of a scene by name do nothing in a scene's ``config``: a folder given, or no name."""
    return folder_given(config) or (None if config.get("scene") is not None else "data.scene=null (no scene by name)")


def neither_given(config: Mapping) -> str | None:
    """What a scene's ``config`` needs where it names neither a folder nor a scene."""
    if config.get("root") is None and config.get("scene") is None:
        return ("a scene's folder, data.root=DIR, or a scene's name, data.scene=NAME (nerfexp-data list names "
                "them; docs/data.md)")
    return None


@dataclass(kw_only=True)
class FolderScene(Scene):
    """A scene read from a folder: ``root``, or, where it is None, the scene ``scene`` names in nerfexp's catalogue or
    the user's ``catalog`` (``nerfexp.data.catalog``), unpacked in the scene cache (``nerfexp.data.scene_cache``).
    ``fetch`` downloads a scene by name into the cache where it is not there (from ``mirror``'s host where set); every
    other member only looks there, with no network access (the commands that read a run back find its scene so).
    ``max_side``: where set, its images are shrunk further, by the smallest whole factor that brings the longer side
    to at most ``max_side`` pixels (so CPU-sized runs fit scenes of any resolution); None: never."""

    DOMAINS: ClassVar[dict[str, Rule]] = {
        **Scene.DOMAINS,
        "root": optional(PATH, "the scene data.scene names"),
        "scene": optional(SCENE_NAME, "data.root's folder"),
        "catalog": optional(PATH, "nerfexp's catalogue alone"),
        "mirror": optional(MIRROR, "each source's own host"),
    }
    APPLIES: ClassVar[dict[str, Applies]] = {  # nerfexp.domains: when an argument does nothing
        "scene": folder_given,
        "catalog": folder_unnamed,
        "mirror": folder_unnamed,
    }
    CONSISTENT: ClassVar[dict[tuple[str, ...], Consistent]] = {("root", "scene"): neither_given,
                                                               ("scene",): scene_problem}

    root: str | None = field(default=None, kw_only=False)  # the one argument a format also takes by position
    scene: str | None = None
    catalog: str | None = None
    mirror: str | None = None
    max_side: int | None = None

    def entry(self) -> Entry:
        """The catalogue entry ``scene`` names (``find_entry``)."""
        return find_entry(self.scene, self.catalog)

    def folder(self) -> Path:
        """The scene's folder: ``root``, else the cache's folder of the scene by name (``cached_folder``)."""
        if self.root is not None:
            return Path(self.root)
        if self.scene is None:
            raise ConfigError(f"data.root=null and data.scene=null: expected {neither_given({})}")
        return cached_folder(self.entry())

    def fetch(self) -> None:
        """A scene by name into the cache (``fetch_scene``), where it is not there already."""
        if self.root is None and self.scene is not None:
            fetch_scene(self.entry(), self.mirror)

    def source(self) -> dict | None:
        """The cache's record of a scene by name (its name, the archive's address, SHA-256 and size, how the digest
        was established and when); None for a folder given."""
        if self.root is not None or self.scene is None:
            return None
        return scene_record(data_cache(), self.entry())
