"""Rays for Lightning: random training batches over all pixels, whole images for evaluation.

The datasets below serve world rays; the loaders' collate step (``model_batch``) turns them into the
model's rays (NDC for forward-facing LLFF scenes) and adds the world view directions as "viewdirs".
"""

import functools
import itertools
from collections.abc import Iterator
from typing import Protocol

import lightning as L
import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, open_dict
from torch import Tensor
from torch.utils.data import DataLoader, Dataset, IterableDataset

from nerfexp.cameras import camera_rays, pixel_directions
from nerfexp.data.views import Views
from nerfexp.errors import ConfigError
from nerfexp.renderer import BACKGROUNDS


class Scene(Protocol):
    """What a dataset format provides (``data`` in the config builds one).

    A scene may also define ``model_rays(origins, directions) -> (origins, directions)``, the rays the
    model renders made from world rays [..., 3] (``LLFFScene``: NDC rays); without it they are the world rays.
    """

    background: str

    def views(self, split: str) -> Views: ...


def fill_ray_bounds(cfg: DictConfig) -> None:
    """Set ``data.near`` and ``data.far`` left null in ``cfg`` (``data=colmap``: they come from the sparse
    points) to the scene's ``bounds()``, in place, so that the renderer built from ``cfg`` and the
    config a run records hold the values used. Values set in the config stay."""
    if cfg.data.get("near") is not None and cfg.data.get("far") is not None:
        return
    near, far = instantiate(cfg.data).bounds()
    with open_dict(cfg.data):
        cfg.data.near, cfg.data.far = float(near), float(far)


def model_batch(scene: Scene, batch: dict) -> dict:
    """A batch of world rays as the model takes it: "origins" and "directions" [..., 3] converted by the
    scene's ``model_rays`` where it has one, and "viewdirs" [..., 3] the world (unit) directions."""
    origins, directions = batch["origins"], batch["directions"]
    convert = getattr(scene, "model_rays", None)
    if convert is not None:
        origins, directions = convert(origins, directions)
    return {**batch, "origins": origins, "directions": directions, "viewdirs": batch["directions"]}


def batch_seeds(seed: int, index: int, rank: int = 0) -> tuple[int, int]:
    """Two independent 63-bit seeds for batch ``index`` of the stream ``seed`` (any ints): one for the
    batch's rays, shared by every process, and one for the training step's own random numbers on
    process ``rank`` (each rank jitters its own rays). Hashed by numpy's ``SeedSequence``, so
    neighbouring seeds, indices and ranks give unrelated streams; rank 0's seeds do not depend on how
    many processes there are."""
    words = np.random.SeedSequence([seed % 2**64, index % 2**64]).generate_state(2 + rank, np.uint64)
    return int(words[0] >> 1), int(words[1 + rank] >> 1)


def rank_slice(batch_rays: int, rank: int, world_size: int) -> slice:
    """The rays of a global batch of ``batch_rays`` that process ``rank`` of ``world_size`` trains on:
    the ``rank``-th of ``world_size`` equal, disjoint, contiguous parts, e.g. rays 256:512 of 1024 on
    rank 1 of 4. ``batch_rays`` must be divisible by ``world_size``."""
    if batch_rays % world_size:
        raise ConfigError(f"scale.batch_rays={batch_rays} is the global batch, split evenly over {world_size} "
                          f"processes (trainer.devices x trainer.num_nodes): choose a multiple of {world_size}")
    share = batch_rays // world_size
    return slice(rank * share, (rank + 1) * share)


class RandomRays(IterableDataset):
    """An endless stream of batches of rays drawn uniformly from all training pixels: this process's
    share of each global batch of ``batch_rays`` rays.

    Each batch is {"origins", "directions", "rgb"}, each [B / world_size, 3], and "seed", an int from
    which the training step draws its own random numbers (the stratified jitter). Rays are computed
    from pixel indices on the fly, so only the images are held in memory.

    Global batch k is a function of (``seed``, k) alone (``batch_seeds``); process ``rank`` of
    ``world_size`` keeps its part ``rank_slice`` of it, so the processes of a distributed run train on
    disjoint rays whose union is the batch one process would draw, and the batch size is the same
    objective on any number of processes. The stream begins at batch ``start``: a run resumed after k
    optimizer steps (``start=k``) draws the batches an uninterrupted run would have drawn.
    """

    def __init__(self, views: Views, background: Tensor, batch_rays: int, seed: int, start: int = 0,
                 rank: int = 0, world_size: int = 1):
        self.rgb = views.rgb_on(background)  # [N, H, W, 3]
        self.c2w = views.c2w
        self.d_cam = pixel_directions(views.height, views.width, views.focal)  # [H, W, 3]
        self.batch_rays, self.seed, self.start = batch_rays, seed, start
        self.rank, self.part = rank, rank_slice(batch_rays, rank, world_size)

    def __iter__(self) -> Iterator[dict[str, Tensor]]:
        N, H, W, _ = self.rgb.shape  # views, rows, columns, channels
        for index in itertools.count(self.start):
            rays_seed, step_seed = batch_seeds(self.seed, index, self.rank)
            generator = torch.Generator().manual_seed(rays_seed)
            n, i, j = (torch.randint(size, (self.batch_rays,), generator=generator)[self.part]
                       for size in (N, H, W))
            rotation = self.c2w[n, :3, :3]  # [B, 3, 3]
            directions = (rotation @ self.d_cam[i, j][..., None]).squeeze(-1)
            yield {"origins": self.c2w[n, :3, 3], "directions": directions, "rgb": self.rgb[n, i, j],
                   "seed": step_seed}


class WholeImages(Dataset):
    """One item per view: {"origins", "directions", "rgb"}, each [H, W, 3], and its "index"."""

    def __init__(self, views: Views, background: Tensor):
        self.views, self.rgb = views, views.rgb_on(background)

    def __len__(self) -> int:
        return len(self.views)

    def __getitem__(self, index: int) -> dict:
        origins, directions = camera_rays(self.views.c2w[index], self.views.height, self.views.width,
                                          self.views.focal)
        return {"origins": origins, "directions": directions, "rgb": self.rgb[index], "index": index}


class RayDataModule(L.LightningDataModule):
    """Loads a scene's splits and serves them as rays: training batches of ``batch_rays`` rays in all
    (the global batch, split over the processes of a distributed run), whole images for evaluation
    (Lightning gives each process every world_size-th image, see ``nerfexp.outputs.gather_evaluations``)."""

    def __init__(self, scene: Scene, batch_rays: int, seed: int = 0):
        super().__init__()
        self.scene, self.batch_rays, self.seed = scene, batch_rays, seed
        self.background = torch.tensor(BACKGROUNDS[scene.background])
        self.splits: dict[str, Views] = {}
        self._collate = functools.partial(model_batch, scene)  # each loader's items -> the model's batches

    def _views(self, split: str) -> Views:
        if split not in self.splits:
            self.splits[split] = self.scene.views(split)
        return self.splits[split]

    def train_dataloader(self) -> DataLoader:
        trainer = self.trainer
        rank, world_size, step = ((trainer.global_rank, trainer.world_size, trainer.global_step)
                                  if trainer is not None else (0, 1, 0))
        # each process its part of the global batch; a resumed run's loader is made after the checkpoint
        # restored the step
        rays = RandomRays(self._views("train"), self.background, self.batch_rays, self.seed, start=step,
                          rank=rank, world_size=world_size)
        return DataLoader(rays, batch_size=None, collate_fn=self._collate)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(WholeImages(self._views("val"), self.background), batch_size=None,
                          collate_fn=self._collate)

    def test_dataloader(self) -> DataLoader:
        return DataLoader(WholeImages(self._views("test"), self.background), batch_size=None,
                          collate_fn=self._collate)
