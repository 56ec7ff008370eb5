import functools
import math

import pytest
import torch
from torch import nn

from nerfexp.nerf.fields import FieldOutputs
from nerfexp.nerf.hierarchy import HierarchyChoice
from nerfexp.nerf.volume_renderer import VolumeRenderer
from tests.analytic import rays_down_z, slab


@pytest.mark.parametrize("shift", [0.0, 0.1, 0.2, -0.13])
@pytest.mark.parametrize("half_width", [0.45, 0.5])
def test_hierarchical_rendering_of_a_slab_converges_to_the_closed_form(shift, half_width, device):
    # A ray down z from z = 4 crosses the slab |z - shift| < w for t in (4 - shift - w, 4 - shift + w):
    # opacity 1 - exp(-3 * 2w), the colour (0.2, 0.4, 0.6) over a white background, and depth
    # E[t | absorbed] of an exponential entering at t0 truncated at length 2w, in closed form.
    s, length = 3.0, 2 * half_width
    exact_opacity = -math.expm1(-s * length)
    t0 = 4 - shift - half_width
    mean_depth = t0 + 1 / s - length * math.exp(-s * length) / exact_opacity
    field = functools.partial(slab, sigma=s, half_width=half_width, shift=shift)
    errors = []
    for n_fine in (16, 256):
        renderer = VolumeRenderer(field, HierarchyChoice(hierarchical=True, n_coarse=8, n_fine=n_fine, n_single=0),
                                  near=2.0, far=6.0).to(device)
        out = renderer(*(x.to(device) for x in rays_down_z(1)), deterministic=True)["fine"]
        errors.append(abs(out["opacity"][0].item() - exact_opacity))
    # 8 coarse samples are 0.5 apart: the coarse error is O(0.1); 256 fine samples resolve the slab.
    assert errors[1] < 2e-3 and errors[1] <= errors[0]
    assert abs(out["depth"][0].item() - mean_depth) < 0.02
    expected_rgb = exact_opacity * torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64) + (1 - exact_opacity)
    torch.testing.assert_close(out["rgb"][0].cpu(), expected_rgb, atol=2e-3, rtol=0)


def test_no_hierarchy_uses_one_network_with_its_own_sample_count():
    renderer = VolumeRenderer(slab, HierarchyChoice(hierarchical=False, n_coarse=8, n_fine=16, n_single=40), near=2.0,
                              far=6.0)
    assert renderer.fine is None and renderer.evaluations_per_ray == 40
    out = renderer(*rays_down_z(2), deterministic=False)
    assert set(out) == {"coarse"} and out["coarse"]["weights"].shape == (2, 40)
    assert VolumeRenderer(slab, HierarchyChoice(True, 8, 16, 40), 2.0, 6.0).evaluations_per_ray == 8 + 24


def test_gradients_flow_to_both_networks(device):
    from nerfexp.nerf.encodings import IdentityEncoding
    from nerfexp.nerf.fields import NeRFField, NoViewDependence

    def field():
        return NeRFField(IdentityEncoding(), NoViewDependence, depth=2, width=16, skips=(),
                         density_activation="softplus")

    renderer = VolumeRenderer(field, HierarchyChoice(True, 8, 8, 16), near=2.0, far=6.0).to(device)
    origins, directions = rays_down_z(3)
    out = renderer(origins.float().to(device), directions.float().to(device), deterministic=False)
    (out["coarse"]["rgb"].sum() + out["fine"]["rgb"].sum()).backward()
    for net in (renderer.coarse, renderer.fine):
        grads = [p.grad for p in net.parameters()]
        assert all(g is not None and torch.isfinite(g).all() for g in grads)
        assert any(g.abs().sum() > 0 for g in grads)


class Fog(nn.Module):
    """Density 0.1 everywhere, white."""

    def forward(self, positions, directions):
        sigma = torch.full(positions.shape[:-1], 0.1, dtype=positions.dtype, device=positions.device)
        return FieldOutputs(rgb=sigma.new_ones(*sigma.shape, 3), sigma=sigma)


def test_hierarchical_rendering_reaches_back_to_near(device):
    # Fog filling [near, far] = [2, 6]: opacity 1 - exp(-0.4). The first coarse sample lies half a spacing
    # past near; the fine samples must still reach [near, t_0], or the fog there is lost for good
    # (an error of e^-0.375 - e^-0.4 = 0.017 with 8 coarse samples, whatever n_fine).
    exact = -math.expm1(-0.4)
    errors = []
    for n_fine in (64, 1024, 16384):
        renderer = VolumeRenderer(Fog, HierarchyChoice(hierarchical=True, n_coarse=8, n_fine=n_fine, n_single=0),
                                  near=2.0, far=6.0).to(device)
        out = renderer(*(x.to(device) for x in rays_down_z(1)), deterministic=True)["fine"]
        errors.append(abs(out["opacity"].item() - exact))
    assert errors[0] < 5e-3 and errors[1] < 3e-4 and errors[2] < 2e-5, errors


def test_the_sparsity_regularizer_is_the_optical_depth_of_the_samples_worked_by_hand():
    # 40 samples at the midpoints of bins 0.1 wide over [2, 6]: t = 2.05, 2.15, ..., 5.95, each standing for
    # [t_i, t_{i+1}] (0.1; the last [5.95, 6]: 0.05). A ray down z from z = 4 is at z = 4 - t: the slab |z| < 0.5
    # holds the 10 samples t = 3.55, ..., 4.45, each 0.1 long: sum sigma delta = 3 * 10 * 0.1 = 3. A ray along
    # x at z = 2 never enters it: 0. The regularizer: weight times the mean over the rays, 0.01 * 1.5.
    renderer = VolumeRenderer(slab, HierarchyChoice(hierarchical=False, n_coarse=8, n_fine=8, n_single=40), near=2.0,
                              far=6.0, sparsity_weight=0.01)
    origins = torch.tensor([[0.0, 0.0, 4.0], [-4.0, 0.0, 2.0]], dtype=torch.float64)
    directions = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    out = renderer(origins, directions, deterministic=True)["coarse"]
    assert out["regularizers"]["sparsity"].item() == pytest.approx(0.01 * (3.0 + 0.0) / 2, rel=1e-12)
    with torch.no_grad():  # a regularizer of training: not computed without gradients
        assert "regularizers" not in renderer(origins, directions, deterministic=True)["coarse"]
    off = VolumeRenderer(slab, HierarchyChoice(hierarchical=False, n_coarse=8, n_fine=8, n_single=40), near=2.0,
                         far=6.0)
    assert "regularizers" not in off(origins, directions, deterministic=True)["coarse"]
