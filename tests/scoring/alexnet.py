"""AlexNet weights for the LPIPS tests, made here (no test needs, or downloads, the ImageNet ones): torchvision's
layout of ``AlexNet.features``, a state dict of random weights in it, and a file of them standing in for the
published one (``stand_in``)."""

import hashlib
import math
from pathlib import Path

import torch
from torch import nn


def torchvision_alexnet_features() -> nn.Sequential:
    """torchvision 0.28's ``AlexNet.features``, written out as torchvision writes it (in-place ReLUs and the
    last max pool included): the layout whose state dict the ImageNet weights file holds."""
    return nn.Sequential(
        nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2), nn.ReLU(inplace=True),
        nn.MaxPool2d(kernel_size=3, stride=2),
        nn.Conv2d(64, 192, kernel_size=5, padding=2), nn.ReLU(inplace=True),
        nn.MaxPool2d(kernel_size=3, stride=2),
        nn.Conv2d(192, 384, kernel_size=3, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(384, 256, kernel_size=3, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(256, 256, kernel_size=3, padding=1), nn.ReLU(inplace=True),
        nn.MaxPool2d(kernel_size=3, stride=2),
    )


def alexnet_state(seed: int = 0) -> dict[str, torch.Tensor]:
    """A state dict as torchvision's AlexNet has (``features.*`` and a classifier entry LPIPS ignores), with
    random weights of a trained network's scale: kernels N(0, 2 / fan-in), biases N(0, 0.1)."""
    generator = torch.Generator().manual_seed(seed)
    state = {}
    for name, value in torchvision_alexnet_features().state_dict().items():
        if name.endswith("weight"):
            fan_in = value[0].numel()
            state[f"features.{name}"] = torch.randn(value.shape, generator=generator) * math.sqrt(2 / fan_in)
        else:
            state[f"features.{name}"] = torch.randn(value.shape, generator=generator) * 0.1
    state["classifier.6.bias"] = torch.zeros(1000)
    return state


def stand_in(monkeypatch, path: Path) -> str:
    """Make the weights file ``path`` stand in for torchvision's published one for the rest of a test: nerfexp's
    pinned digest (``nerfexp.scoring.perceptual.ALEXNET_SHA256``) set to the file's SHA-256, which it returns.
    Only a file of that digest scores ``lpips``; the ImageNet file itself is on no test machine."""
    from nerfexp.scoring import perceptual

    digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()
    monkeypatch.setattr(perceptual, "ALEXNET_SHA256", digest)
    return digest
