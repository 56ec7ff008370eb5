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
from nerfexp.errors import ConfigError, DatasetError
from nerfexp.geometry.cameras import camera_rays
from nerfexp.geometry.lenses import pixel_grid, pixel_rays


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
    """An endless stream of batches of rays drawn uniformly from all training pixels (those the views' mask
    keeps, where they have one): this process's share of each global batch of ``batch_rays`` rays.

    Each batch is {"origins", "directions", "rgb"}, each [B / world_size, 3], "view" [B / world_size] (the
    training view each ray comes from: per-image components index their codes and poses by it), and "seed",
    an int from which the training step draws its own random numbers (the stratified jitter). Rays are made from
    pixel indices on the fly, from the camera-space directions of each distinct lens (``lens_directions``,
    one [H, W, 3] grid per lens: most captures share one lens).

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
        self.lens_of, self.d_cam = lens_directions(views)  # [N] -> [L, H, W, 3]: each distinct lens's rays
        self.batch_rays, self.seed, self.start = batch_rays, seed, start
        self.rank, self.part = rank, rank_slice(batch_rays, rank, world_size)
        self.kept = None if views.mask is None else kept_pixels(views.mask)  # [M]: the flat indices that count

    def __iter__(self) -> Iterator[dict[str, Tensor]]:
        N, H, W, _ = self.rgb.shape  # views, rows, columns, channels
        for index in itertools.count(self.start):
            rays_seed, step_seed = batch_seeds(self.seed, index, self.rank)
            generator = torch.Generator().manual_seed(rays_seed)
            if self.kept is None:
                n, i, j = (torch.randint(size, (self.batch_rays,), generator=generator)[self.part]
                           for size in (N, H, W))
            else:  # one draw among the kept pixels
                flat = self.kept[torch.randint(len(self.kept), (self.batch_rays,), generator=generator)[self.part]]
                n, i, j = torch.unravel_index(flat.long(), (N, H, W))
            rotation = self.c2w[n, :3, :3]  # [B, 3, 3]
            directions = (rotation @ self.d_cam[self.lens_of[n], i, j][..., None]).squeeze(-1)
            yield {"origins": self.c2w[n, :3, 3], "directions": directions, "rgb": self.rgb[n, i, j],
                   "view": n, "seed": step_seed}


def lens_directions(views: Views) -> tuple[Tensor, Tensor]:
    """The camera-space ray directions of every pixel of each distinct lens among ``views`` (most captures
    share one; ``nerfexp.geometry.lenses.pixel_rays``, in ``views.c2w``'s dtype), made once: ``(lens_of
    [N], directions [L, H, W, 3])``, view n's rays ``directions[lens_of[n]]``."""
    lenses = views.intrinsics
    rows = torch.cat([lenses.params, lenses.distortion, lenses.fisheye[:, None].to(lenses.params.dtype)], -1)
    distinct, lens_of = torch.unique(rows, dim=0, return_inverse=True)
    first = torch.stack([(lens_of == k).nonzero()[0, 0] for k in range(len(distinct))])  # a view of each lens
    grid = pixel_grid(views.height, views.width, dtype=views.c2w.dtype)  # [H, W, 2]
    return lens_of, pixel_rays(grid, lenses[first].to(views.c2w.dtype).unsqueeze(2))


def kept_pixels(mask: Tensor) -> Tensor:
    """The flat indices [M] (into [N, H, W]) of the pixels ``mask`` [N, H, W] keeps, int32 where they fit; a
    DatasetError where it keeps none."""
    flat = mask.flatten().nonzero().squeeze(-1)
    if not len(flat):
        raise DatasetError("the training views' masks keep no pixel: every pixel is masked out")
    return flat.int() if mask.numel() < 2 ** 31 else flat


class WholeImages(Dataset):
    """One item per view: {"origins", "directions", "rgb"}, each [H, W, 3], its "index", and where the views
    have a mask its "mask" [H, W] bool (the pixels scored)."""

    def __init__(self, views: Views, background: Tensor):
        self.views, self.rgb = views, views.rgb_on(background)

    def __len__(self) -> int:
        return len(self.views)

    def __getitem__(self, index: int) -> dict:
        origins, directions = camera_rays(self.views.c2w[index], self.views.height, self.views.width,
                                          self.views.intrinsics[index])
        item = {"origins": origins, "directions": directions, "rgb": self.rgb[index], "index": index}
        return item if self.views.mask is None else {**item, "mask": self.views.mask[index]}
