"""The test protocols of per-image appearance (TestScorer.protocol_scores, nerfexp.nerf.appearance.PROTOCOLS):
NeRF-W's fit of a test image's code leaves the networks as they were, and the right half is the pixels scored."""

import functools
import math

import pytest
import torch
from hydra.utils import instantiate
from torch import nn

from nerfexp.nerf.appearance import FULL_IMAGE, NERFW_RIGHT_HALF
from nerfexp.nerf.fields import FieldOutputs
from nerfexp.nerf.hierarchy import HierarchyChoice
from nerfexp.nerf.volume_renderer import VolumeRenderer
from nerfexp.training.module import NeRFModule
from tests.helpers import tiny_config

H, W = 24, 24  # rows, columns of the test images here


class OpaqueColour(nn.Module):
    """Opaque from the first sample on (sigma 1e6: exp(-3e6) is 0 in float32), of one colour: every pixel renders
    exactly ``colour``."""

    def __init__(self, colour: float):
        super().__init__()
        self.colour = colour

    def forward(self, positions, directions):
        sigma = torch.full(positions.shape[:-1], 1e6)
        return FieldOutputs(rgb=torch.full((*sigma.shape, 3), self.colour), sigma=sigma)


def image_batch(rgb: torch.Tensor, mask: torch.Tensor | None = None) -> dict:
    directions = nn.functional.normalize(torch.randn(H, W, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    batch = {"origins": -4 * directions, "directions": directions, "rgb": rgb, "index": 3}
    return batch if mask is None else {**batch, "mask": mask}


def constant_module(colour: float, protocol: str) -> NeRFModule:
    renderer = VolumeRenderer(lambda: OpaqueColour(colour), HierarchyChoice(True, 4, 4, 8), 2.0, 6.0)
    return NeRFModule(renderer, functools.partial(torch.optim.Adam, lr=1e-3), lr_final=1e-4, chunk=100,
                      lpips=False, test_protocol=protocol)


@pytest.mark.parametrize("protocol", [FULL_IMAGE, NERFW_RIGHT_HALF])
def test_the_right_half_is_scored_over_the_pixels_its_mask_keeps(protocol):
    """The render is 0.2 (51/255) everywhere; the target's left half is noise and its right half 0.2 but for one
    pixel of 0.8 (204/255). Masked out, the right half matches exactly (PSNR inf); kept, the MSE is that pixel's
    0.6^2 over the right half's 24 x 12 pixels: PSNR = -10 log10(0.36 / 288) = 29.031 dB."""
    torch.manual_seed(0)
    target = torch.full((H, W, 3), 51 / 255)
    target[:, : W // 2] = torch.rand(H, W // 2, 3)
    target[5, 20] = 204 / 255
    mask = torch.ones(H, W, dtype=torch.bool)
    mask[5, 20] = False
    m = constant_module(51 / 255, protocol)
    masked = m.test_step(image_batch(target, mask), 0)
    kept = m.test_step(image_batch(target), 0)
    assert masked["psnr_right_half"] == math.inf
    assert kept["psnr_right_half"] == pytest.approx(-10 * math.log10(0.36 / 288), abs=1e-9)
    assert kept["psnr_full_image"] < 15  # the noisy left half counts in the whole image
    headline = "psnr_full_image" if protocol == FULL_IMAGE else "psnr_right_half"
    assert kept["psnr"] == kept[headline] and kept["ssim"] == kept[headline.replace("psnr", "ssim")]
    assert kept["rgb"].shape == (H, W, 3)  # the render kept is the whole image's under either protocol


def test_nerfw_protocol_fits_the_code_alone_and_leaves_the_networks_bit_for_bit():
    cfg = tiny_config("appearance=embedding", "appearance.fit.steps=5", "appearance.fit.rays=32", "model.lpips=false")
    torch.manual_seed(0)
    m = instantiate(cfg.model).eval()
    m.renderer.appearance.set_views(4)
    with torch.no_grad():
        m.renderer.appearance.codes.copy_(torch.randn(4, m.renderer.appearance.dim))
    before = {key: value.clone() for key, value in m.state_dict().items()}
    batch = image_batch(torch.rand(H, W, 3))
    with torch.inference_mode():  # as Lightning's test loop runs it
        code = m.test_scorer().fitted_code(batch)
        scores = m.test_step(batch, 0)
    assert not torch.equal(code, m.renderer.appearance.test_code())  # the code moved
    after = m.state_dict()
    assert all(torch.equal(before[key], after[key]) for key in before)  # codes and networks as they were
    assert all(p.grad is None for p in m.parameters())
    assert scores["psnr"] == scores["psnr_right_half"] and math.isfinite(scores["psnr_full_image"])
    with torch.inference_mode():
        assert torch.equal(m.test_scorer().fitted_code(batch), code)  # seeded by the image's index: the same fit again
