import functools
import math

import pytest
import torch
from torch import nn

from nerfexp.renderer import VolumeRenderer


class Slab(nn.Module):
    """An analytic field: density ``sigma`` where |z - shift| < half_width, else 0; colour (0.2, 0.4, 0.6)."""

    def __init__(self, sigma=3.0, half_width=0.5, shift=0.0):
        super().__init__()
        self.sigma, self.half_width, self.shift = sigma, half_width, shift

    def forward(self, positions, directions):
        inside = (positions[..., 2] - self.shift).abs() < self.half_width
        sigma = torch.where(inside, self.sigma, 0.0).to(positions.dtype)
        rgb = torch.tensor([0.2, 0.4, 0.6], dtype=positions.dtype).expand(*positions.shape[:-1], 3)
        return rgb, sigma


def rays_down_z(n):
    origins = torch.zeros(n, 3, dtype=torch.float64)
    origins[:, 2] = 4.0
    directions = torch.zeros(n, 3, dtype=torch.float64)
    directions[:, 2] = -1.0
    return origins, directions


@pytest.mark.parametrize("shift", [0.0, 0.1, 0.2, -0.13])
@pytest.mark.parametrize("half_width", [0.45, 0.5])
def test_hierarchical_rendering_of_a_slab_converges_to_the_closed_form(shift, half_width):
    # A ray down z from z = 4 crosses the slab |z - shift| < w for t in (4 - shift - w, 4 - shift + w):
    # opacity 1 - exp(-3 * 2w), the colour (0.2, 0.4, 0.6) over a white background, and depth
    # E[t | absorbed] of an exponential entering at t0 truncated at length 2w, in closed form.
    s, length = 3.0, 2 * half_width
    exact_opacity = -math.expm1(-s * length)
    t0 = 4 - shift - half_width
    mean_depth = t0 + 1 / s - length * math.exp(-s * length) / exact_opacity
    field = functools.partial(Slab, sigma=s, half_width=half_width, shift=shift)
    errors = []
    for n_fine in (16, 256):
        renderer = VolumeRenderer(field, hierarchical=True, n_coarse=8, n_fine=n_fine, n_single=0, near=2.0, far=6.0)
        out = renderer(*rays_down_z(1), deterministic=True)["fine"]
        errors.append(abs(out["opacity"][0].item() - exact_opacity))
    # 8 coarse samples are 0.5 apart: the coarse error is O(0.1); 256 fine samples resolve the slab.
    assert errors[1] < 2e-3 and errors[1] <= errors[0]
    assert abs(out["depth"][0].item() - mean_depth) < 0.02
    expected_rgb = exact_opacity * torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64) + (1 - exact_opacity)
    torch.testing.assert_close(out["rgb"][0], expected_rgb, atol=2e-3, rtol=0)


def test_no_hierarchy_uses_one_network_with_its_own_sample_count():
    renderer = VolumeRenderer(Slab, hierarchical=False, n_coarse=8, n_fine=16, n_single=40, near=2.0, far=6.0)
    assert renderer.fine is None and renderer.evaluations_per_ray == 40
    out = renderer(*rays_down_z(2), deterministic=False)
    assert set(out) == {"coarse"} and out["coarse"]["weights"].shape == (2, 40)
    assert VolumeRenderer(Slab, True, 8, 16, 40, 2.0, 6.0).evaluations_per_ray == 8 + 24


def test_gradients_flow_to_both_networks():
    from nerfexp.encodings import IdentityEncoding
    from nerfexp.fields import DiffuseHead, NeRFField

    def field():
        return NeRFField(IdentityEncoding(), DiffuseHead, depth=2, width=16, skips=(), density_activation="softplus")

    renderer = VolumeRenderer(field, True, 8, 8, 16, near=2.0, far=6.0)
    origins, directions = rays_down_z(3)
    out = renderer(origins.float(), directions.float(), deterministic=False)
    (out["coarse"]["rgb"].sum() + out["fine"]["rgb"].sum()).backward()
    for net in (renderer.coarse, renderer.fine):
        grads = [p.grad for p in net.parameters()]
        assert all(g is not None and torch.isfinite(g).all() for g in grads)
        assert any(g.abs().sum() > 0 for g in grads)


def test_bf16_mixed_training_keeps_rendering_in_float32(monkeypatch):
    # A real training run under Lightning's bf16-mixed precision on the CPU: the network's matrix
    # products run in bf16, yet every rendering call gets float32 densities, and training stays finite.
    import lightning as L
    from torch.utils.data import DataLoader

    import nerfexp.renderer as renderer_module
    from nerfexp.encodings import PositionalEncoding
    from nerfexp.fields import NeRFField, ViewMLPHead
    from nerfexp.module import NeRFModule

    rendered_dtypes = []
    original = renderer_module.render_weights

    def recording_render_weights(sigmas, t_starts, t_ends):
        rendered_dtypes.append(sigmas.dtype)
        return original(sigmas, t_starts, t_ends)

    monkeypatch.setattr(renderer_module, "render_weights", recording_render_weights)
    head = functools.partial(ViewMLPHead, direction_encoding=PositionalEncoding(2), hidden=16)
    field = functools.partial(NeRFField, PositionalEncoding(4), head, depth=3, width=32, skips=(1,),
                              density_activation="softplus", density_bias=-1.0)
    torch.manual_seed(0)
    renderer = VolumeRenderer(field, hierarchical=True, n_coarse=8, n_fine=8, n_single=16, near=2.0, far=6.0)
    network_dtypes = set()
    renderer.coarse.trunk[0].register_forward_hook(lambda m, i, out: network_dtypes.add(out.dtype))
    module = NeRFModule(renderer, functools.partial(torch.optim.Adam, lr=1e-3), lr_final=1e-4)
    directions = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1)
    batch = {"origins": -4 * directions, "directions": directions, "rgb": torch.rand(64, 3)}
    trainer = L.Trainer(accelerator="cpu", precision="bf16-mixed", max_steps=5, logger=False,
                        enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
                        limit_val_batches=0)
    trainer.fit(module, train_dataloaders=DataLoader([batch] * 5, batch_size=None))
    assert trainer.global_step == 5
    assert torch.bfloat16 in network_dtypes  # autocast was on for the network
    assert rendered_dtypes and set(rendered_dtypes) == {torch.float32}
    assert all(torch.isfinite(p).all() for p in module.parameters())
    # the bf16 render is the float32 render to bf16's precision (8 significant bits)
    with torch.no_grad():
        exact = renderer(batch["origins"], directions, deterministic=True)["fine"]
        with torch.autocast("cpu", dtype=torch.bfloat16):
            mixed = renderer(batch["origins"], directions, deterministic=True)["fine"]
    assert mixed["rgb"].dtype == torch.float32 and mixed["depth"].dtype == torch.float32
    torch.testing.assert_close(mixed["rgb"], exact["rgb"], atol=0.03, rtol=0)


class Fog(nn.Module):
    """Density 0.1 everywhere, white."""

    def forward(self, positions, directions):
        sigma = torch.full(positions.shape[:-1], 0.1, dtype=positions.dtype)
        return torch.ones(*sigma.shape, 3, dtype=positions.dtype), sigma


def test_hierarchical_rendering_reaches_back_to_near():
    # Fog filling [near, far] = [2, 6]: opacity 1 - exp(-0.4). The first coarse sample lies half a spacing
    # past near; the fine samples must still reach [near, t_0], or the fog there is lost for good
    # (an error of e^-0.375 - e^-0.4 = 0.017 with 8 coarse samples, whatever n_fine).
    exact = -math.expm1(-0.4)
    errors = []
    for n_fine in (64, 1024, 16384):
        renderer = VolumeRenderer(Fog, hierarchical=True, n_coarse=8, n_fine=n_fine, n_single=0, near=2.0, far=6.0)
        out = renderer(*rays_down_z(1), deterministic=True)["fine"]
        errors.append(abs(out["opacity"].item() - exact))
    assert errors[0] < 5e-3 and errors[1] < 3e-4 and errors[2] < 2e-5, errors
