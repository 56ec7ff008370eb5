"""Rays for Lightning: random training batches over all pixels, whole images for evaluation."""

from collections.abc import Iterator
from typing import Protocol

import lightning as L
import torch
from torch import Tensor
from torch.utils.data import DataLoader, Dataset, IterableDataset

from nerfexp.cameras import camera_rays, pixel_directions
from nerfexp.data.views import Views
from nerfexp.renderer import BACKGROUNDS


class Scene(Protocol):
    """What a dataset format provides (``data`` in the config builds one)."""

    background: str

    def views(self, split: str) -> Views: ...


class RandomRays(IterableDataset):
    """An endless stream of batches of ``batch_rays`` rays drawn uniformly from all training pixels.

    Each batch is {"origins", "directions", "rgb"}, each [B, 3]. Rays are computed from pixel
    indices on the fly, so only the images are held in memory. ``seed`` makes the stream repeatable.
    """

    def __init__(self, views: Views, background: Tensor, batch_rays: int, seed: int):
        self.rgb = views.rgb_on(background)  # [N, H, W, 3]
        self.c2w = views.c2w
        self.d_cam = pixel_directions(views.height, views.width, views.focal)  # [H, W, 3]
        self.batch_rays, self.seed = batch_rays, seed

    def __iter__(self) -> Iterator[dict[str, Tensor]]:
        generator = torch.Generator().manual_seed(self.seed)
        N, H, W, _ = self.rgb.shape  # views, rows, columns, channels
        while True:
            n, i, j = (torch.randint(size, (self.batch_rays,), generator=generator) for size in (N, H, W))
            rotation = self.c2w[n, :3, :3]  # [B, 3, 3]
            directions = (rotation @ self.d_cam[i, j][..., None]).squeeze(-1)
            yield {"origins": self.c2w[n, :3, 3], "directions": directions, "rgb": self.rgb[n, i, j]}


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
    """Loads a scene's splits and serves them as rays."""

    def __init__(self, scene: Scene, batch_rays: int, seed: int = 0):
        super().__init__()
        self.scene, self.batch_rays, self.seed = scene, batch_rays, seed
        self.background = torch.tensor(BACKGROUNDS[scene.background])
        self.splits: dict[str, Views] = {}

    def _views(self, split: str) -> Views:
        if split not in self.splits:
            self.splits[split] = self.scene.views(split)
        return self.splits[split]

    def train_dataloader(self) -> DataLoader:
        rank = self.trainer.global_rank if self.trainer is not None else 0  # each process its own stream
        rays = RandomRays(self._views("train"), self.background, self.batch_rays, self.seed + rank)
        return DataLoader(rays, batch_size=None)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(WholeImages(self._views("val"), self.background), batch_size=None)

    def test_dataloader(self) -> DataLoader:
        return DataLoader(WholeImages(self._views("test"), self.background), batch_size=None)
