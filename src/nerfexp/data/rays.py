"""Rays from posed views: random training batches over all pixels, whole images for evaluation, and the
conversion of world rays into the rays the model renders (``model_batch``)."""

import itertools
from collections.abc import Iterator

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import Dataset, IterableDataset

from nerfexp.data.base import Scene
from nerfexp.data.views import Views
from nerfexp.errors import ConfigError
from nerfexp.geometry.cameras import camera_rays, pixel_directions


def model_batch(scene: Scene, batch: dict) -> dict:
    """A batch of world rays as the model takes it: "origins" and "directions" [..., 3] converted by the
    scene's ``model_rays``, and "viewdirs" [..., 3] the world (unit) directions."""
    origins, directions = scene.model_rays(batch["origins"], batch["directions"])
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
