"""The recipes of docs/developing.md, followed from the tests' own folder: a toy encoding, a toy colour head and a
toy sampler (each a class and a config file, nothing of nerfexp edited) compose, are checked by their own domains
and train under every acceleration and every scale; the sampler is sized by a scale key of its own, checked by its
domains; the encoding sweeps beside the paper's positional encoding and reaches the report."""

import csv
import json
import math
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate
from omegaconf import OmegaConf

import nerfexp.conf
from nerfexp.errors import ConfigError
from nerfexp.nerf.samplers import Rays
from nerfexp.settings.checks import check_settings
from tests.components.toy import MidpointSampler, PowerEncoding, TiltViewDependence
from tests.helpers import REPO, TINY, one_error_line, run_nerfexp

SEARCH = f"hydra.searchpath=[file://{REPO / 'tests' / 'components'}]"  # where encoding/toy.yaml lies
CONF = Path(nerfexp.conf.__file__).parent
ACCELERATIONS = sorted(path.stem for path in (CONF / "acceleration").glob("*.yaml"))  # every option: none, occupancy
SCALES = sorted(path.stem for path in (CONF / "scale").glob("*.yaml"))  # cpu, paper
# Each recipe's group (its toy: GROUP=toy), and the TINY overrides its toy leaves unread, which a single run refuses:
# the toy head has no hidden layer, the toy sampler no hierarchy
RECIPES = {"encoding": (), "view_dependence": ("scale.view_hidden=",), "sampler": ("scale.n_coarse=", "scale.n_fine=")}


def tiny(group: str) -> list[str]:
    """TINY without the overrides ``group``'s toy leaves unread: each stays its scale's (scale=paper's, ...)."""
    return [o for o in TINY if not o.startswith(RECIPES[group])]


def test_the_toy_encoding_maps_each_coordinate_to_its_powers():
    x = torch.tensor([[2.0, -1.0, 0.5]])
    assert torch.equal(PowerEncoding(n_powers=3, gain=0.5)(x), 0.5 * torch.tensor([[2.0, -1.0, 0.5, 4.0, 1.0, 0.25,
                                                                                   8.0, -1.0, 0.125]]))


def composed(*overrides: str):
    with initialize_config_module("nerfexp.conf", version_base=None):
        return compose("config", overrides=[SEARCH, *overrides], return_hydra_config=True)


def test_it_composes_into_the_field_and_its_own_domains_check_it():
    cfg = composed("encoding=toy")
    assert cfg.model.renderer.field.position_encoding._target_ == "tests.components.toy.PowerEncoding"
    check_settings(cfg)  # its keys have rules: the class's DOMAINS, nothing central
    with pytest.raises(ConfigError, match=r"^encoding.position.n_powers=0: expected a whole number in \[1, "):
        check_settings(composed("encoding=toy", "encoding.position.n_powers=0"))
    model = instantiate(cfg.model)
    assert model.renderer.coarse.trunk[0].in_features == 9  # 3 coordinates x 3 powers


@pytest.mark.slow
def test_it_trains_sweeps_beside_posenc_and_reaches_the_report(tmp_path):
    bad = run_nerfexp(*TINY, SEARCH, "encoding=toy", "encoding.position.gain=100",
                      f"hydra.run.dir={tmp_path / 'bad'}", cwd=tmp_path)
    assert one_error_line(bad) == "nerfexp: error: encoding.position.gain=100: expected a finite number > 0 and <= 16"
    sweep = tmp_path / "sweep"
    done = run_nerfexp("-m", *TINY, SEARCH, "encoding=posenc,toy", f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    report = run_nerfexp(str(sweep), cwd=tmp_path, script="nerfexp-report")
    assert report.returncode == 0, report.stderr[-3000:]
    with open(sweep / "report.csv") as file:
        rows = {row["variant"]: row for row in csv.DictReader(file)}
    assert set(rows) == {"encoding=posenc", "encoding=toy"}
    assert all(row["finished"] == "1" for row in rows.values())
    assert rows["encoding=toy"]["n_params"] != rows["encoding=posenc"]["n_params"]  # 9 inputs, not 63


def test_the_toy_colour_head_is_the_sigmoid_of_its_linear_colour_tilted_by_the_direction():
    head = TiltViewDependence(in_features=2, tilt=2.0)
    with torch.no_grad():
        head.rgb.weight.copy_(torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]))
        head.rgb.bias.zero_()
    h = torch.tensor([[[1.0, -1.0]]])  # [rays, samples, features]: logits (1, -1, 0) before the tilt
    d = torch.tensor([[[0.0, 0.0, 1.0]]])  # looking along z: only blue is tilted, by 2
    expected = torch.tensor([[[1.0, -1.0, 2.0]]]).sigmoid()
    assert torch.allclose(head(h, d), expected, rtol=0, atol=1e-7)


def test_the_toy_colour_head_composes_into_the_field_and_is_checked_by_its_domains():
    cfg = composed("view_dependence=toy")
    check_settings(cfg)
    with pytest.raises(ConfigError, match=r"^view_dependence.tilt=9: expected a finite number >= -8 and <= 8"):
        check_settings(composed("view_dependence=toy", "view_dependence.tilt=9"))
    model = instantiate(cfg.model)
    head = model.renderer.coarse.view_head
    assert isinstance(head, TiltViewDependence) and head.tilt == 2.0
    assert head.rgb.in_features == cfg.model.renderer.field.width  # built from the trunk's width


class RecordedSteps:
    """The renderer's two steps as a sampler sees them, recording the samples asked for."""

    def __init__(self):
        self.asked = []

    def composited(self, name, rays, t):
        self.asked.append((name, t))
        return {"rgb": torch.zeros(len(t), 3)}

    def density_weights(self, network, rays, t):
        raise AssertionError("the toy sampler has no density-only network")


def test_the_toy_sampler_asks_for_the_midpoints_of_equal_bins_of_each_ray():
    rays = Rays(torch.zeros(2, 3), torch.ones(2, 3), torch.ones(2, 3) / 3 ** 0.5, torch.tensor([2.0, 0.0]),
                torch.tensor([6.0, 1.0]))
    steps = RecordedSteps()
    out = MidpointSampler(n_samples=4).render(rays, steps, deterministic=False)
    assert set(out) == {"coarse"} and [name for name, _ in steps.asked] == ["coarse"]
    # [2, 6] in 4 bins of 1: midpoints 2.5 .. 5.5; [0, 1] in 4 bins of 1/4: 1/8, 3/8, 5/8, 7/8
    assert torch.equal(steps.asked[0][1], torch.tensor([[2.5, 3.5, 4.5, 5.5], [0.125, 0.375, 0.625, 0.875]]))


def test_the_toy_sampler_composes_into_the_renderer_and_is_checked_by_its_domains():
    cfg = composed("sampler=toy")
    check_settings(cfg)
    with pytest.raises(ConfigError, match=r"^sampler.n_samples=0: expected a whole number in \[1, "):
        check_settings(composed("sampler=toy", "sampler.n_samples=0"))
    renderer = instantiate(cfg.model).renderer
    assert isinstance(renderer.sampler, MidpointSampler) and renderer.samples_per_ray == 24
    assert renderer.fine is None  # one field, the sampler's only name


@pytest.mark.parametrize(("scale", "samples"), [("cpu", 24), ("paper", 64)])  # tests/components/sampler/toy_sizes/
def test_the_toy_samplers_own_scale_key_is_checked_by_the_argument_it_lands_in(scale, samples):
    cfg = composed("sampler=toy", f"scale={scale}")
    assert cfg.scale.toy_samples == samples and cfg.sampler.n_samples == samples
    check_settings(cfg)  # scale.toy_samples has a rule, the sampler's DOMAINS: nothing in nerfexp names it
    with pytest.raises(ConfigError) as error:
        check_settings(composed("sampler=toy", f"scale={scale}", "scale.toy_samples=0"))
    assert str(error.value) == ("scale.toy_samples=0 (which sets sampler.n_samples): expected a whole number in "
                                "[1, 2^63 - 1]")
    with pytest.raises(ConfigError, match=r"^scale.toy_samples=24: not a setting nerfexp reads"):
        check_settings(composed("+scale.toy_samples=24"))  # without the toy sampler nothing reads it


@pytest.mark.parametrize("scale", SCALES)
@pytest.mark.parametrize("acceleration", ACCELERATIONS)
@pytest.mark.parametrize("group", RECIPES)
def test_each_recipe_trains_under_every_acceleration_and_scale(tmp_path, group, acceleration, scale):
    # scale=paper shrunk by TINY's overrides of its own keys: its learning rates, chunk and test stride stay the paper's
    overrides = [*tiny(group), f"{group}=toy", f"acceleration={acceleration}", f"scale={scale}", "scale.steps=8",
                 "scale.val_every=8", "test_budgets=[]"]
    cfg = composed(*overrides)
    check_settings(cfg)
    renderer = instantiate(cfg.model).renderer
    run = tmp_path / "run"
    done = run_nerfexp(SEARCH, *overrides, f"hydra.run.dir={run}", cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    results = json.loads((run / "results.json").read_text())
    assert {key: results["choices"][key] for key in (group, "acceleration", "scale")} \
        == {group: "toy", "acceleration": acceleration, "scale": scale}
    assert results["steps"] == 8 and math.isfinite(results["test_psnr"])
    assert results["config"]["scale"] == OmegaConf.to_container(cfg.scale)  # trained at that scale
    if renderer.grid is None:  # every sample the sampler places is evaluated
        assert results["evaluations_per_ray"] == renderer.samples_per_ray
    else:  # the grid skips the empty ones
        assert 0 < results["evaluations_per_ray"] < renderer.samples_per_ray
