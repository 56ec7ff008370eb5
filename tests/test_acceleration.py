"""The occupancy grid through the real config and the command line: every component trains with packed
samples, an accelerated sweep is reported as its own variant, and an accelerated run resumes exactly."""

import itertools
import json

import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate

from nerfexp.data.procedural import objects_box
from tests.analytic import aimed_rays
from tests.helpers import TINY, final_state, kill_at, read_json, run_nerfexp


@pytest.fixture(scope="module")
def accelerated_configs():
    with initialize_config_module("nerfexp.conf", version_base=None):
        return {(e, v, h): compose("config", overrides=[
            "acceleration=occupancy", f"encoding={e}", f"view_dependence={v}", f"hierarchical={h}",
            "scale.depth=2", "scale.width=16", "scale.skips=[1]", "scale.view_hidden=8"])
            for e, v, h in itertools.product(["none", "posenc"], ["mlp", "none", "sh", "ref"],
                                             [True, False, "proposal"])}


@pytest.mark.parametrize("encoding", ["none", "posenc"])
@pytest.mark.parametrize("view_dependence", ["mlp", "none", "sh", "ref"])
@pytest.mark.parametrize("hierarchical", [True, False, "proposal"])
def test_every_component_trains_packed(accelerated_configs, encoding, view_dependence, hierarchical):
    cfg = accelerated_configs[(encoding, view_dependence, hierarchical)]
    torch.manual_seed(0)
    renderer = instantiate(cfg.model.renderer)
    renderer.grid.set_bounds(objects_box())
    renderer.grid.update(0, renderer.density_fns())
    origins, directions = (t.float() for t in aimed_rays(64, torch.Generator().manual_seed(0), 0.8, (3.5, 4.5)))
    outputs = renderer(origins, directions, deterministic=False)
    loss = sum(out["rgb"].square().mean() + sum(out.get("regularizers", {}).values()) for out in outputs.values())
    loss.backward()
    assert torch.isfinite(loss)
    assert all(torch.isfinite(p.grad).all() for p in renderer.parameters() if p.grad is not None)
    assert 0 < renderer.stats["samples_per_ray"] < renderer.samples_per_ray
    renderer.grid.occupied.zero_()  # nothing left to evaluate: an empty packed batch renders the background
    out = renderer(origins, directions, deterministic=True)
    assert torch.equal(out["coarse"]["rgb"], torch.ones(64, 3)) and renderer.stats["samples_per_ray"] == 0


@pytest.mark.slow
def test_a_short_accelerated_run_trains_and_is_its_own_variant_in_the_report(tmp_path):
    sweep = tmp_path / "sweep"
    result = run_nerfexp("-m", *TINY, "acceleration=none,occupancy", f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    report = run_nerfexp(str(sweep), cwd=tmp_path, script="nerfexp-report")
    assert report.returncode == 0, report.stderr[-3000:]
    text = (sweep / "report.md").read_text()
    rows = [line for line in text.splitlines() if line.startswith("| acceleration=")]
    assert len(rows) == 2 and any(row.startswith("| acceleration=occupancy |") for row in rows), text
    accelerated = [json.loads(path.read_text()) for path in sweep.glob("*/results.json")]
    accelerated = {r["choices"]["acceleration"]: r for r in accelerated}
    assert accelerated["occupancy"]["test_psnr"] > 10  # white is about 8.5 dB on this scene
    # 60 steps are within the warm-up, whose few updates have emptied little yet: what is left out is mostly
    # outside the scene's box, [-1.5, 1.5]^3, which holds about three quarters of [near, far] of rays aimed at it
    assert accelerated["occupancy"]["evaluations_per_ray"] < 0.85 * accelerated["none"]["evaluations_per_ray"]


@pytest.mark.slow
def test_an_accelerated_run_killed_and_resumed_ends_as_the_uninterrupted_run(tmp_path):
    # The grid (its box, density estimates and occupied cells) is part of the checkpoint, and its
    # updates draw from the step's seeded random numbers: the resumed run is bit-identical.
    accelerated = [*TINY, "acceleration=occupancy", "acceleration.grid.warmup_steps=16",
                   "acceleration.grid.update_every=4"]
    alone, killed = tmp_path / "alone", tmp_path / "killed"
    for run_dir, extra in ((alone, []), (killed, kill_at(30))):
        run_dir.mkdir()
        run_nerfexp(*accelerated, *extra, f"hydra.run.dir={run_dir}", cwd=run_dir, new_process=bool(extra))
    assert final_state(killed)["step"] == 30
    resumed = run_nerfexp(*accelerated, f"resume={killed}/checkpoints/last.ckpt", f"hydra.run.dir={killed}",
                          cwd=killed)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    state, expected = final_state(killed)["weights"], final_state(alone)["weights"]
    assert {"renderer.grid.aabb", "renderer.grid.density", "renderer.grid.occupied"} <= set(expected)
    assert state.keys() == expected.keys() and all(torch.equal(state[k], expected[k]) for k in expected)
    assert expected["renderer.grid.density"].min() > 0  # every cell was evaluated (warm-up)
    assert read_json(killed / "results.json")["evaluations_per_ray"] < 48  # of 16 + (16 + 16) samples
