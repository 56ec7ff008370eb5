"""A row means its label: every row of the paper's table runs on every scene format with the views it names,
and a row beside a choice on one of its axes is refused in one line before any work."""

from importlib.resources import files

import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate

from nerfexp.data.blender import write_blender
from nerfexp.data.llff import write_llff
from nerfexp.data.procedural import TRAIN_VIEWS
from nerfexp.data.views import Views
from nerfexp.errors import ConfigError
from nerfexp.geometry.cameras import look_at
from nerfexp.geometry.lenses import Intrinsics
from nerfexp.settings.checks import check_settings
from nerfexp.settings.rows import check_row
from nerfexp.settings.unused import check_used
from tests.helpers import one_error_line, run_nerfexp

ROWS = sorted(p.name.removesuffix(".yaml") for p in (files("nerfexp.conf") / "ablation").iterdir()
              if p.name.endswith(".yaml"))
FEWER = {"fewer_images": 50, "far_fewer_images": 25}  # Table 4's images; the other rows train on all
N_VIEWS = 64  # each written scene's images: more training views than the fewer-images rows keep
SIDE = 8  # pixels: the test reads views, it trains nothing


def cameras(n: int) -> torch.Tensor:
    """``n`` cameras [n, 4, 4] float64 on a small grid in front of the origin, all looking at it (forward-facing,
    as an LLFF scene's)."""
    k = torch.arange(n, dtype=torch.float64)
    eyes = torch.stack([(k % 8 - 3.5) * 0.05, (k // 8 - 3.5) * 0.05, torch.full_like(k, 4.0)], -1)
    return look_at(eyes, torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> dict[str, list[str]]:
    """The overrides of a scene of each format: Blender and LLFF scenes written with ``N_VIEWS`` images."""
    images = torch.rand(N_VIEWS, SIDE, SIDE, 3, generator=torch.Generator().manual_seed(0))
    c2w = cameras(N_VIEWS)
    blender, llff = tmp_path_factory.mktemp("blender"), tmp_path_factory.mktemp("llff")
    rgba = torch.cat([images, torch.ones_like(images[..., :1])], -1)
    for split, views in (("train", slice(0, N_VIEWS)), ("val", slice(0, 2)), ("test", slice(0, 2))):
        lenses = Intrinsics.pinhole(10.0, SIDE, SIDE, (len(rgba[views]),))
        write_blender(blender, split, Views(rgba=rgba[views], c2w=c2w[views].float(), intrinsics=lenses), 0.7)
    write_llff(llff, images, c2w, 10.0, torch.tensor([[3.0, 5.0]] * N_VIEWS))
    return {"procedural": ["data=procedural", f"scale.image_size={SIDE}", "data.supersample=1"],
            "blender": ["data=blender", f"data.root={blender}"],
            "llff": ["data=llff", f"data.root={llff}", "data.factor=1"]}


def composed(*overrides: str):
    with initialize_config_module("nerfexp.conf", version_base=None):
        return compose("config", overrides=list(overrides), return_hydra_config=True)


@pytest.mark.parametrize("row", ROWS)
def test_every_row_runs_on_every_format_with_the_views_it_names(scenes, row):
    for name, scene in scenes.items():
        cfg = composed(f"ablation={row}", *scene)
        check_settings(cfg)
        check_row(cfg, cfg.hydra.runtime.choices, list(cfg.hydra.overrides.task))
        check_used(cfg, list(cfg.hydra.overrides.task))
        train = instantiate(cfg.data).views("train")
        every = TRAIN_VIEWS if name == "procedural" else N_VIEWS - N_VIEWS // 8  # LLFF: every 8th a test view
        if name == "blender":
            every = N_VIEWS
        assert len(train.rgba) == FEWER.get(row, every), (row, name)
        instantiate(cfg.model)  # the row's model builds on this format


def test_a_colmap_scene_takes_every_row_too(tmp_path):
    # its splits are LLFF's rule (nerfexp.data.views.holdout_split, with n_train); reconstruction is tested there
    for row in ROWS:
        cfg = composed(f"ablation={row}", "data=colmap", f"data.root={tmp_path}")
        check_settings(cfg)
        check_row(cfg, cfg.hydra.runtime.choices, list(cfg.hydra.overrides.task))
        assert instantiate(cfg.data).n_train == FEWER.get(row)


@pytest.mark.parametrize(("overrides", "clash"), [
    (["encoding=hashgrid", "ablation=no_posenc"], "encoding=hashgrid and ablation=no_posenc"),
    (["ablation=complete", "hierarchical=false"], "hierarchical=false and ablation=complete"),
    (["ablation=no_hierarchical", "hierarchical=proposal"], "hierarchical=proposal and ablation=no_hierarchical"),
    (["ablation=complete", "encoding.position.n_freqs=12"], "encoding.position.n_freqs=12 and ablation=complete"),
    (["ablation=fewer_images", "data.n_train=25"], "data.n_train=25 and ablation=fewer_images"),
    (["ablation=no_view_dependence", "view_dependence=sh"], "view_dependence=sh and ablation=no_view_dependence"),
])
def test_a_row_and_a_choice_on_its_axis_are_refused_in_one_line(overrides, clash):
    cfg = composed(*overrides)
    with pytest.raises(ConfigError) as refused:
        check_row(cfg, cfg.hydra.runtime.choices, list(cfg.hydra.overrides.task))
    assert str(refused.value).startswith(f"{clash}: the row trains ")
    assert "so its label would name another variant: drop one of them" in str(refused.value)


def test_what_a_row_does_not_set_stays_the_users(scenes):
    for overrides in (["ablation=complete", "seed=3", "scale.steps=10", "acceleration=occupancy"],
                      ["ablation=no_posenc", "encoding=none"],  # the row's own choice, said again
                      ["ablation=fewer_images", *scenes["llff"]]):
        cfg = composed(*overrides)
        check_row(cfg, cfg.hydra.runtime.choices, list(cfg.hydra.overrides.task))


def test_the_command_line_refuses_it_before_the_run_directory_is_made(tmp_path):
    result = run_nerfexp("encoding=hashgrid", "ablation=no_posenc", f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert one_error_line(result).startswith("nerfexp: error: encoding=hashgrid and ablation=no_posenc: the row trains "
                                             "encoding=none, view_dependence=mlp, hierarchical=true")
    assert not (tmp_path / "run").exists()


def test_a_row_with_a_preset_that_changes_its_axes_is_refused_in_one_line():
    # experiment=fast chooses the hash grid after the row chose the positional encoding: the row's label would
    # name another variant
    cfg = composed("ablation=complete", "experiment=fast")
    with pytest.raises(ConfigError) as refused:
        check_row(cfg, cfg.hydra.runtime.choices, list(cfg.hydra.overrides.task))
    assert str(refused.value).startswith("ablation=complete with encoding=hashgrid: the row trains encoding=posenc")
