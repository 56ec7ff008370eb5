"""AlexNet weights for the LPIPS tests, made here (no test needs, or downloads, the ImageNet ones): torchvision's
layout of ``AlexNet.features`` and a state dict of random weights in it."""

import math

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
