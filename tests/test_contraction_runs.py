"""Scene contraction (``contraction=mipnerf360``) through the real config and the command line: it trains with every
sampler, with the hash grid and the occupancy grid (whose boxes become the contraction's), its inner region is
fit to the training cameras and kept in the checkpoint, and an export meshes the inner region at world
positions."""

import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate

from nerfexp.data.procedural import scene_cameras
from nerfexp.nerf.bounds import Bounded
from nerfexp.nerf.contraction import SceneContraction
from nerfexp.products.mesh import export_box, final_field
from nerfexp.rundir.layout import LAST_CHECKPOINT
from tests.analytic import aimed_rays
from tests.helpers import TINY, read_json, run_nerfexp


@pytest.mark.parametrize("hierarchical", [True, False, "proposal"])
@pytest.mark.parametrize("encoding", ["posenc", "hashgrid"])
def test_every_sampler_and_encoding_trains_contracted_through_the_grid(hierarchical, encoding):
    with initialize_config_module("nerfexp.conf", version_base=None):
        cfg = compose("config", overrides=["contraction=mipnerf360", "acceleration=occupancy", f"encoding={encoding}",
                                           f"hierarchical={hierarchical}", "scale.depth=2",
                                           "scale.width=16", "scale.skips=[1]", "scale.view_hidden=8",
                                           *(["encoding.position.log2_table_size=10"] if encoding == "hashgrid"
                                             else [])])
    torch.manual_seed(0)
    renderer = instantiate(cfg.model.renderer)
    renderer.contraction.set_inner(torch.zeros(3, dtype=torch.float64), 1.5)
    for module in renderer.modules():  # as the module does when training starts
        if isinstance(module, Bounded):
            module.set_bounds(renderer.contraction.box)
    renderer.grid.update(0, renderer.density_fns())
    origins, directions = (t.float() for t in aimed_rays(64, torch.Generator().manual_seed(0), 0.8, (3.5, 4.5)))
    outputs = renderer(origins, directions, deterministic=False)
    loss = sum(out["rgb"].square().mean() + sum(out.get("regularizers", {}).values()) for out in outputs.values())
    loss.backward()
    assert torch.isfinite(loss)
    grads = [p.grad for p in renderer.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    for out in outputs.values():  # samples reach far beyond the objects: spaced in disparity up to 1000 radii
        assert out["t_starts"].amax() > 10


def test_a_contracted_run_fits_its_inner_region_to_the_cameras_and_keeps_it(tmp_path):
    run_dir = tmp_path / "run"
    result = run_nerfexp(*TINY, "contraction=mipnerf360", "encoding=hashgrid", "field=nerf", "acceleration=occupancy",
                         "encoding.position.log2_table_size=10", "model.lpips=false",
                         f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert read_json(run_dir / "results.json")["choices"]["contraction"] == "mipnerf360"
    state = torch.load(run_dir / LAST_CHECKPOINT, map_location="cpu", weights_only=True)["state_dict"]
    # the built-in scene's training cameras lie on a sphere of radius 4 around the origin, above the ground
    centres = scene_cameras("train", 12)[:, :3, 3]
    torch.testing.assert_close(state["renderer.contraction.centre"], centres.mean(0))
    radius = torch.linalg.vector_norm(centres - centres.mean(0), dim=-1).max()
    torch.testing.assert_close(state["renderer.contraction.radius"], radius)
    box = torch.tensor([[-2.0] * 3, [2.0] * 3])
    assert torch.equal(state["renderer.grid.aabb"], box)
    assert torch.equal(state["renderer.coarse.position_encoding.aabb"], box)


def test_a_contracted_field_is_exported_over_its_inner_region_at_world_positions():
    contraction = SceneContraction("l2", centre=[1.0, 0.0, 0.0], radius=2.0)

    class Probe(torch.nn.Module):  # density: the first coordinate of the position it is given
        def density(self, positions):
            return positions[..., 0]

    renderer = torch.nn.Module()
    renderer.fine, renderer.coarse, renderer.contraction = Probe(), None, contraction
    renderer.field_positions = contraction
    field = final_field(renderer)
    world = torch.tensor([[1.0, 0, 0], [2.0, 0, 0], [101.0, 0, 0]])
    # inner units (x - 1) / 2: 0, 0.5, 50 -> contracted 0, 0.5, 2 - 1/50
    torch.testing.assert_close(field.density(world), torch.tensor([0.0, 0.5, 1.98]))
    torch.testing.assert_close(export_box(renderer, scene=None), torch.tensor([[-1.0, -2, -2], [3.0, 2, 2]],
                                                                              dtype=torch.float64))
