"""The settings schema (nerfexp.settings): every key of every group option has a rule, values across and
beyond each domain are refused in one ConfigError naming the key or build, and unused overrides are named; the
commands that read a run back check their overrides and arguments alike."""

import math
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf, open_dict

import nerfexp.conf
from nerfexp.commands import evaluate, export, render, view
from nerfexp.commands.arguments import run_settings
from nerfexp.data.datamodule import fill_ray_bounds
from nerfexp.errors import ConfigError, NerfexpError
from nerfexp.products.frames import frame_size, render_frame, training_path
from nerfexp.products.trained import load_module, load_run
from nerfexp.rundir.layout import LAST_CHECKPOINT, RUN_CONFIG
from nerfexp.rundir.trained import run_config
from nerfexp.settings.checks import check_run_settings, check_settings, checked_settings
from nerfexp.settings.schema import lightning_precisions, rule_of
from nerfexp.settings.unused import unused_settings
from nerfexp.training.precision import fill_precision
from tests.helpers import TINY

GROUPS = {  # every option of every group (conf/), and the sweeps' configs
    "encoding": ["hashgrid", "none", "posenc"], "view_dependence": ["mlp", "none", "ref", "sh"],
    "data": ["blender", "colmap", "llff", "procedural"], "scale": ["cpu", "paper"],
    "trainer": ["bf16", "ddp", "default", "slurm"], "acceleration": ["none", "occupancy"],
    "camera_opt": ["off", "so3xr3"],
    "callbacks": ["default"], "logger": ["csv", "mlflow", "none", "tensorboard", "wandb"],
    "ablation": ["complete", "far_fewer_images", "fewer_frequencies", "fewer_images", "more_frequencies",
                 "no_hierarchical", "no_pe_vd_h", "no_posenc", "no_view_dependence"],
    "experiment": ["fast"],
    "+sweeps": ["components", "cpu_ablation", "paper_ablation", "paper_ablation_blender", "smoke", "successors"],
}


@pytest.fixture(scope="module")
def hydra_configs():
    with initialize_config_module("nerfexp.conf", version_base=None):
        yield


def test_every_key_of_every_option_has_a_rule(hydra_configs):
    for group, options in GROUPS.items():
        for option in options:
            cfg = compose("config", overrides=[f"{group}={option}", "++data.root=/x"])  # the folder scenes need
            uncovered = [key for key, _ in checked_settings(cfg) if rule_of(cfg, key) is None]
            assert not uncovered, f"{group}={option}: keys with no rule (a component's DOMAINS or SCHEMA): {uncovered}"


def composed(*overrides):
    """The TINY config with ``overrides``, as a job sees it but without Hydra's runtime (a test's cwd)."""
    return compose("config", overrides=[*TINY, *overrides, "trainer.default_root_dir=."])


@pytest.mark.parametrize(("overrides", "message"), [
    (["seed=abc"], "seed=abc: expected a whole number in [0, 4294967295]"),
    (["seed=-1"], "seed=-1: expected a whole number in [0, 4294967295]"),
    (["trainer.precision=bogus"], "trainer.precision=bogus: expected one of "),
    (["view_dependence=sh", "view_dependence.degree=7"], "view_dependence.degree=7: expected a whole number in [0, 3]"),
    (["scale.image_size=0"], "scale.image_size=0 (which sets data.image_size): expected a whole number in [1, "
                             "2^63 - 1]"),
    (["scale.lr=nan"], "scale.lr=nan (which sets model.optimizer.lr): expected a finite number > 0"),
    (["callbacks.guard.on_nonfinite=ignore"], "callbacks.guard.on_nonfinite=ignore: expected one of stop, skip"),
    (["data.background=grey"], "data.background=grey (which sets model.renderer.background): expected one of "),
    (["data.aabb=[[0,0,0],[1,1]]"], "data.aabb=[[0, 0, 0], [1, 1]]: expected [[x0, y0, z0]"),
    (["hierarchical=maybe"], "hierarchical=maybe: expected one of true, false, proposal"),
    (["hierarchical=1"], "hierarchical=1: expected one of true, false, proposal"),
    (["hierarchical=proposal", "proposal.n_samples=[]"], "proposal.n_samples=[]: expected a non-empty list of "),
    (["hierarchical=proposal", "proposal.interlevel_weight=0"], "proposal.interlevel_weight=0: expected a finite "
                                                                "number > 0"),
    # a component's arguments that do not fit together (its CONSISTENT), each named as the user sets it
    (["scale.skips=[5]"], "scale.skips=[5] (which sets model.renderer.field.skips), scale.depth=2 (which sets "
                          "model.renderer.field.depth): expected layer indices in 1..1 for depth 2"),
    (["hierarchical=proposal", "proposal.network.skips=[2]"], "proposal.network.skips=[2], proposal.network.depth=2: "
                                                              "expected layer indices in 1..1 for depth 2"),
    (["+foo=1"], "foo=1: not a setting nerfexp reads"),
    (["scale.lr=???"], "missing mandatory value: scale.lr (set it"),  # not model.optimizer.lr, which reads it
    (["data.near=5", "data.far=2"], "data.near=5 (which sets model.renderer.near), data.far=2 (which sets "
                                    "model.renderer.far): expected near < far"),
    (["data.near=2", "data.far=2"], "data.near=2 (which sets model.renderer.near), data.far=2"),
    # a memory estimate names every setting it multiplies, so the one the user set among them (issue 39)
    (["scale.image_size=100000"], "scale.image_size=100000 (which sets data.image_size), data.supersample=2, "
                                  "data.n_train=12, data.n_val=1, data.n_test=2: a scene of 15 views of 100000 x "
                                  "100000 pixels needs about "),
    (["data.n_test=10000000000"], "scale.image_size=24 (which sets data.image_size), data.supersample=2, "
                                  "data.n_train=12, data.n_val=1, data.n_test=10000000000: a scene of 10000000013 "
                                  "views of 24 x 24 pixels needs about "),
    (["scale.batch_rays=100000000"], "scale.batch_rays=100000000 (which sets datamodule.batch_rays), scale.n_coarse=16 "
                                     "(which sets sampler.n_coarse), scale.n_fine=16 (which sets "
                                     "sampler.n_fine), scale.width=32 (which sets "
                                     "model.renderer.field.width), "
                                     "scale.depth=2 (which sets model.renderer.field.depth): a training batch of "
                                     "100000000 rays x 48 samples through 2 layers of 32 units needs about"),
    (["scale.width=100000000"], "scale.batch_rays=256 (which sets datamodule.batch_rays), scale.n_coarse=16 (which "
                                "sets sampler.n_coarse), scale.n_fine=16 (which sets "
                                "sampler.n_fine), "
                                "scale.width=100000000 (which sets model.renderer.field.width), scale.depth=2"),
    (["scale.width=1000000", "scale.batch_rays=1", "scale.chunk=1"],  # the weights alone: depth x width^2
     "scale.width=1000000 (which sets model.renderer.field.width), scale.depth=2 (which sets "
     "model.renderer.field.depth): training a field of 2 layers of 1000000 units needs about"),
    (["hierarchical=proposal", "proposal.network.width=2000000"], "proposal.network.width=2000000, "
                                                                 "proposal.network.depth=2: training a proposal "),
    (["encoding=hashgrid", "encoding.position.n_levels=100000000"], "encoding.position.n_levels=100000000, "
                                                                    "encoding.position.log2_table_size=16, "
                                                                    "encoding.position.features_per_level=2: a hash "
                                                                    "encoding of 100000000 levels needs about"),
    (["acceleration=occupancy", "acceleration.grid.resolution=100000"], "acceleration.grid.resolution=100000: an "
                                                                        "occupancy grid of 100000^3 cells needs"),
    # a test-time fit's step renders its rays with the outputs kept for its backward pass, as a training batch:
    # 2^40 rays x 48 samples x (8 + 2 x 32) floats x 4 bytes = 2^40 x 13824 bytes = 13.5 PiB
    (["appearance=embedding", "appearance.fit.rays=1099511627776"],
     "appearance.fit.rays=1099511627776, scale.n_coarse=16 (which sets "
     "sampler.n_coarse), scale.n_fine=16 (which sets sampler.n_fine), scale.width=32 (which sets "
     "model.renderer.field.width), scale.depth=2 (which sets model.renderer.field.depth): a step of the test "
     "images' appearance fit of 1099511627776 rays x 48 samples through 2 layers of 32 units needs about 13.5 PiB"),
    (["test_cameras=refined", "test_cameras.fit.rays=1099511627776"],
     "test_cameras.fit.rays=1099511627776, scale.n_coarse=16 (which sets "
     "sampler.n_coarse), scale.n_fine=16 (which sets sampler.n_fine), scale.width=32 (which sets "
     "model.renderer.field.width), scale.depth=2 (which sets model.renderer.field.depth): a step of the test "
     "cameras' fit of 1099511627776 rays x 48 samples through 2 layers of 32 units needs about 13.5 PiB"),
    # 12 codes x 2^40 numbers x 4 copies (the code, its gradient, Adam's two moments) x 4 bytes = 192 TiB
    (["appearance=embedding", "appearance.embedding.dim=1099511627776"],
     "appearance.embedding.dim=1099511627776, data.n_train=12: training "
     "the appearance codes of 12 views of 1099511627776 numbers needs about 192 TiB"),
    (["scale.image_size=" + "9" * 400], f"scale.image_size={'9' * 400} (which sets data.image_size): expected a "
                                        "whole number in [1, 2^63 - 1]"),
    # every number has an upper bound where it stops meaning anything (issue 39 section 4)
    (["encoding=hashgrid", "encoding.position.log2_table_size=40"], "encoding.position.log2_table_size=40: "
                                                                    "expected a whole number in [1, 30]"),
    (["encoding=hashgrid", "scale=paper", "encoding.position.finest=18446744073709551616"],
     "encoding.position.finest=18446744073709551616: expected a whole number in [1, 1048575]"),
    (["encoding=hashgrid", "encoding.position.coarsest=100", "encoding.position.finest=50"],
     "encoding.position.coarsest=100, encoding.position.finest=50: expected coarsest <= finest"),
    (["data.far=1e308"], "data.far=1e+308 (which sets model.renderer.far): expected a finite number > 0 and <= 2^24"),
    (["data.near=inf"], "data.near=inf (which sets model.renderer.near): expected a finite number >= 0 and <= 2^24"),
    (["data.aabb=[[0,0,0],[1e30,1,1]]"], "data.aabb=[[0, 0, 0], [1e+30, 1, 1]]: expected [[x0, y0, z0], [x1, y1, "
                                         "z1]] of numbers within +-2^24"),
    (["model.chunk=0"], "model.chunk=0: expected a whole number in [1, 2^63 - 1]"),
    (["scale.steps=9223372036854775808"], "scale.steps=9223372036854775808 (which sets "),
    (["scale.lr=2"], "scale.lr=2 (which sets model.optimizer.lr): expected a finite number > 0 and <= 1"),
    (["model.renderer.field.density_bias=1e30"], "model.renderer.field.density_bias=1e+30: expected a finite number "
                                                 ">= -88 and <= 88"),
    (["model.renderer.field.density_noise_std=18446744073709551616"], "model.renderer.field.density_noise_std="),
    (["data.far=" + "9" * 400], f"data.far={'9' * 400} (which sets model.renderer.far): expected a finite number > "
                                "0 and <= 2^24"),  # a whole number past any float: compared, never converted
    (["scale.position_input_scale=1e300"], "scale.position_input_scale=1e+300 (which sets "
                                           "encoding.position.input_scale): expected a finite number > 0 and <= "),
    (["hierarchical=proposal", "proposal.distortion_weight=1e30"], "proposal.distortion_weight=1e+30: expected a "
                                                                   "finite number >= 0 and <= 2^24"),
    (["contraction=mipnerf360", "contraction.function.norm=l1"], "contraction.function.norm=l1: expected one of "
                                                                 "l2, linf"),
    (["contraction=mipnerf360", "contraction.function.radius=0"], "contraction.function.radius=0: expected a "
                                                                  "finite number > 0"),
    (["contraction=mipnerf360", "contraction.function.centre=[0,1]"], "contraction.function.centre=[0, 1]: "
                                                                      "expected a list of 3 items, each a finite "
                                                                      "number within +-2^24, or null"),
    # a point and a distance in scene units: within 2^24, where float32 positions still resolve a unit
    (["contraction=mipnerf360", "contraction.function.centre=[0,0,1e30]"], "contraction.function.centre=[0, 0, "
                                                                           "1e+30]: expected a list of 3 items, each "
                                                                           "a finite number within +-2^24"),
    (["contraction=mipnerf360", "contraction.function.radius=1e30"], "contraction.function.radius=1e+30: expected "
                                                                     "a finite number > 0 and <= 2^24"),
    # counts of threads and processes per node beyond any machine's CPUs (2^16), physical quantities in their ranges
    (["threads=65537"], "threads=65537: expected a whole number in [1, 65536], or null (auto: the CPUs"),
    (["threads=0"], "threads=0: expected a whole number in [1, 65536]"),
    (["trainer.devices=1000000"], "trainer.devices=1000000: expected a whole number in [1, 65536], a list of device "
                                  "indices, or auto"),
    (["datamodule.pose_noise=[181,0]"], "datamodule.pose_noise=[181, 0]: expected [degrees, fraction of the cameras' "
                                        "radius], degrees a finite number in [0, 180] and fraction one in [0, 1]"),
    (["datamodule.pose_noise=[2,1.5]"], "datamodule.pose_noise=[2, 1.5]: expected [degrees, fraction of the "
                                        "cameras' radius]"),
    (["contraction=mipnerf360", "contraction.function.far=1"], "contraction.function.far=1: expected a finite "
                                                               "number > 1"),
])
def test_a_value_out_of_its_domain_is_one_error_naming_the_key(hydra_configs, overrides, message):
    with pytest.raises(ConfigError) as error:
        check_settings(composed(*overrides))
    assert str(error.value).startswith(message), str(error.value)


@pytest.mark.parametrize(("value", "message"), [
    (100000, "data.threads=100000: expected -1 (every CPU this process may use) or a whole number in [1, 65536]"),
    (0, "data.threads=0: expected -1"),
    (-2, "data.threads=-2: expected -1"),
])
def test_colmaps_thread_count_is_bounded_as_torchs(hydra_configs, value, message):
    with pytest.raises(ConfigError) as error:
        check_settings(compose("config", overrides=["data=colmap", "data.root=/nowhere", f"data.threads={value}"]))
    assert str(error.value).startswith(message), str(error.value)


@pytest.mark.parametrize("overrides", [
    ["threads=65536"], ["threads=1"], ["trainer.devices=2"], ["trainer.devices=[0]"], ["trainer.devices=auto"],
    ["datamodule.pose_noise=[180,1]"], ["datamodule.pose_noise=[0,0]"], ["datamodule.pose_noise=null"],
    ["contraction=mipnerf360", "contraction.function.centre=[0,0,16777216]", "contraction.function.radius=16777216"],
])
def test_the_bounds_themselves_are_settings(hydra_configs, overrides):
    check_settings(composed(*overrides))


def test_a_contraction_of_ndc_rays_is_refused_in_one_line(hydra_configs):
    cfg = compose("config", overrides=["contraction=mipnerf360", "data=llff", "data.root=/nowhere"])
    with pytest.raises(ConfigError) as error:
        check_settings(cfg)
    assert str(error.value) == ("contraction=mipnerf360 and data.ndc=true: NDC rays already bound a "
                                "forward-facing scene's depth; set data.ndc=false (with data.near and data.far) to "
                                "contract world positions, or contraction=none")
    check_settings(compose("config", overrides=["contraction=mipnerf360", "data=llff", "data.root=/nowhere",
                                                "data.ndc=false", "data.near=0.1"]))


SCALE_FILES = sorted((Path(nerfexp.conf.__file__).parent / "scale").glob("*.yaml"))  # every option: cpu, paper


@pytest.mark.parametrize("choices", [[], ["encoding=hashgrid", "view_dependence=sh", "hierarchical=false"]])
@pytest.mark.parametrize("scale_file", SCALE_FILES, ids=lambda path: path.stem)
def test_every_size_of_the_scale_is_checked_where_it_lands_or_refused_as_unused(hydra_configs, scale_file, choices):
    # no scale key has a rule of its own (nerfexp.settings.schema.readers_rule): a value no domain holds (a text) is
    # refused as the key it lands in expects, or, where this config reads the key nowhere (scale.lr with the hash
    # grid's optimizer), as unused; never as not a setting, nor let through
    cfg = compose("config", overrides=[*TINY, f"scale={scale_file.stem}", *choices, "trainer.default_root_dir=."],
                  return_hydra_config=True)
    for key in OmegaConf.load(scale_file):
        bad = cfg.copy()
        OmegaConf.update(bad, f"scale.{key}", "abc")
        override = f"scale.{key}=abc"
        try:
            check_settings(bad)
        except ConfigError as error:
            assert str(error).startswith(f"{override} (which sets "), str(error)
            assert ": expected " in str(error), str(error)
            continue
        assert [o for o, _ in unused_settings(bad, [override])] == [override], f"{override} let through"


def test_a_scale_key_whose_reader_the_user_set_directly_is_still_a_setting_with_its_readers_rule(hydra_configs):
    # model.chunk: ${scale.chunk} in config.yaml; set directly, nothing in the run reads scale.chunk any more,
    # which stays a setting checked by the rule of the key nerfexp's own config has read it (model.chunk's)
    check_settings(composed("model.chunk=100"))
    with pytest.raises(ConfigError, match=r"^scale.chunk=abc: expected "):
        check_settings(composed("model.chunk=100", "scale.chunk=abc"))
    assert [o for o, _ in unused_settings(composed("model.chunk=100"), ["model.chunk=100", "scale.chunk=64"])] \
        == ["scale.chunk=64"]


def test_an_override_that_does_not_apply_is_named_with_the_reason(hydra_configs):
    cfg = composed("hierarchical=false", "scale.n_fine=64")
    assert [o for o, _ in unused_settings(cfg, ["hierarchical=false", "scale.n_fine=64", "seed=1"])] \
        == ["scale.n_fine=64"]
    assert unused_settings(cfg, ["scale.n_single=8"]) == []  # used without the hierarchy
    assert [o for o, _ in unused_settings(composed("view_dependence=sh"), ["scale.view_hidden=8"])] \
        == ["scale.view_hidden=8"]
    # the third choice on the sampling axis reads its own keys, and not the hierarchy's sample counts
    proposal = composed("hierarchical=proposal")
    assert unused_settings(proposal, ["proposal.n_final=16", "proposal.network.width=32"]) == []
    assert [o for o, _ in unused_settings(proposal, ["scale.n_fine=64", "scale.n_single=8"])] \
        == ["scale.n_fine=64", "scale.n_single=8"]
    # the scene's box serves the grids alone (the scene's SERVES, their SCENE_FIELDS): unused without one, used with
    # either; the scene's other keys are its own
    box = "data.aabb=[[0,0,0],[1,1,1]]"
    with_choices = compose("config", overrides=[*TINY, "trainer.default_root_dir=."], return_hydra_config=True)
    assert unused_settings(with_choices, [box, "data.n_train=10"]) == [
        (box, "acceleration=none (acceleration=occupancy reads data.aabb); encoding=posenc (encoding=hashgrid reads "
              "data.aabb)")]
    assert unused_settings(composed("acceleration=occupancy"), [box]) == []
    assert unused_settings(composed("encoding=hashgrid"), [box]) == []
    # a contraction's grids work in its own box: the scene's box does nothing
    contracted = composed("contraction=mipnerf360", "acceleration=occupancy")
    assert unused_settings(contracted, ["data.aabb=[[0,0,0],[1,1,1]]", "data.far=100"]) == [
        ("data.aabb=[[0,0,0],[1,1,1]]", "contraction=mipnerf360 (the grids work in the contraction's box, [-2, 2]^3)"),
        ("data.far=100", "contraction=mipnerf360 (rays end contraction.function.far radii away)")]
    assert [reason for _, reason in unused_settings(composed(), ["proposal.n_final=16"])] == [
        "hierarchical=true (a coarse network of sampler.n_coarse samples and a fine one of n_coarse + "
        "n_fine; set scale.n_coarse and scale.n_fine)"]


def test_lpips_settings_are_checked_before_any_work_and_may_change_on_resume(hydra_configs, tmp_path, monkeypatch):
    from nerfexp.training.resume import may_differ

    monkeypatch.setenv("TORCH_HOME", str(tmp_path))  # an empty torch hub cache
    check_settings(composed())  # auto: the run goes on without the weights, and says so when it starts
    check_settings(composed("model.lpips=false"))
    with pytest.raises(ConfigError, match=f"^model.lpips=true: no AlexNet ImageNet weights at {tmp_path}/hub/"):
        check_settings(composed("model.lpips=true"))
    with pytest.raises(ConfigError, match="^model.lpips_weights=/no/such.pth: no such file; expected torchvision's "
                                          r"AlexNet ImageNet weights \(alexnet-owt-7be5be79.pth\)"):
        check_settings(composed("model.lpips_weights=/no/such.pth"))
    with pytest.raises(ConfigError, match="^model.lpips=maybe: expected one of auto, true, false$"):
        check_settings(composed("model.lpips=maybe"))
    assert unused_settings(composed("model.lpips=false"), ["model.lpips=false", "model.lpips_weights=/x.pth"]) == [
        ("model.lpips_weights=/x.pth", "model.lpips=false (LPIPS is not scored)")]
    assert may_differ("model.lpips") and may_differ("model.lpips_weights")  # what is scored, not what is trained


def test_own_lpips_weights_need_a_file_are_unused_without_lpips_and_may_change_on_resume(hydra_configs, tmp_path,
                                                                                       monkeypatch):
    from nerfexp.training.resume import may_differ

    monkeypatch.setenv("TORCH_HOME", str(tmp_path))  # an empty torch hub cache
    with pytest.raises(ConfigError, match="^model.lpips_custom=true says the AlexNet weights model.lpips_weights "
                                          "names are your own, and it names none"):
        check_settings(composed("model.lpips_custom=true"))
    with pytest.raises(ConfigError, match="^model.lpips_custom=maybe: expected true or false$"):
        check_settings(composed("model.lpips_custom=maybe"))
    check_settings(composed("model.lpips=false", "model.lpips_custom=true"))  # nothing read
    assert unused_settings(composed("model.lpips=false"), ["model.lpips=false", "model.lpips_custom=true"]) == [
        ("model.lpips_custom=true", "model.lpips=false (LPIPS is not scored)")]
    assert may_differ("model.lpips_custom")


VALUES = st.one_of(  # across and beyond the domains: wrong types, negatives, zero, nan, huge, strings
    st.integers(-3, 5), st.integers(2 ** 31, 2 ** 64), st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(), st.sampled_from(["abc", "", "null", "stop", "skip", "white", "32-true", "auto"]),
)
KEYS = ["seed", "hierarchical", "scale.lr", "scale.batch_rays", "scale.depth", "scale.width", "scale.n_coarse",
        "scale.n_fine", "scale.chunk", "scale.image_size", "scale.position_input_scale", "scale.lr_warmup_steps",
        "data.n_train", "data.n_val", "data.supersample", "data.near", "data.far", "data.background",
        "encoding.position.n_freqs", "encoding.direction.n_freqs", "view_dependence.hidden",
        "callbacks.guard.on_nonfinite", "callbacks.guard.max_skips", "trainer.precision", "trainer.max_steps",
        "model.renderer.field.density_bias", "model.optimizer.eps", "model.lpips",
        "model.renderer.field.density_noise_std", "encoding.position.input_scale", "scale.steps"]


def override(key, value) -> str:
    text = "null" if value is None else str(value).lower() if isinstance(value, bool) else repr(value) \
        if isinstance(value, str) else str(value)
    return f"{key}={text}" if not (isinstance(value, float) and not math.isfinite(value)) else f"{key}={value}"


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.tuples(st.sampled_from(KEYS), VALUES), min_size=1, max_size=3))
def test_any_setting_is_refused_in_one_error_naming_it_or_builds(hydra_configs, changes):
    cfg = composed()
    for key, value in changes:
        OmegaConf.update(cfg, key, value)
    try:
        check_settings(cfg)
    except ConfigError as error:
        assert any(key in str(error) for key, _ in changes) or "which sets" in str(error), str(error)
        return
    instantiate(cfg.model)
    fill_precision(cfg)  # as a job does before it builds the trainer
    instantiate(cfg.trainer, logger=False, callbacks=[], enable_checkpointing=False)
    instantiate(cfg.datamodule)  # the scene: small enough by the check's own estimate


# The commands that read a run back (nerfexp-eval, -render, -export, -view) check its saved config with the user's
# KEY=VALUE overrides as nerfexp checks a new run's (nerfexp.settings.checks.check_run_settings; issue 39)

@pytest.fixture(scope="module")
def saved_run(hydra_configs, tmp_path_factory):
    """A run directory as training leaves one, made without training: the TINY config (its scene smaller still)
    saved where Hydra saves it and a checkpoint of the untrained model (the commands read any run back alike)."""
    run_dir = tmp_path_factory.mktemp("saved_run")
    cfg = composed("scale.image_size=8", "data.n_train=4", "data.supersample=1")
    (run_dir / RUN_CONFIG).parent.mkdir()
    OmegaConf.save(cfg, run_dir / RUN_CONFIG)
    built = cfg.copy()
    fill_ray_bounds(built)  # as load_module does: the scene's near and far where the config leaves them null
    (run_dir / LAST_CHECKPOINT).parent.mkdir()
    torch.save({"state_dict": instantiate(built.model).state_dict(), "global_step": 0}, run_dir / LAST_CHECKPOINT)
    return run_dir


@pytest.mark.parametrize(("command", "arguments", "message"), [
    (evaluate, ["model.chunk=0"], "nerfexp-eval: error: model.chunk=0: expected a whole number in [1, 2^63 - 1]"),
    (evaluate, ["data.near=inf"], "nerfexp-eval: error: data.near=inf (which sets model.renderer.near): expected a "
                                  "finite number >= 0 and <= 2^24, or null (from the scene)"),
    (render, ["scale.chunk=0"], "nerfexp-render: error: scale.chunk=0 (which sets model.chunk): expected a whole "
                                "number in [1, 2^63 - 1]"),
    (export, ["data.far=1e308"], "nerfexp-export: error: data.far=1e+308 (which sets model.renderer.far): expected a "
                                 "finite number > 0 and <= 2^24, or null (from the scene)"),
    (view, ["data.n_test=10000000000"], "nerfexp-view: error: scale.image_size=8 (which sets data.image_size), "
                                        "data.supersample=1, data.n_train=4, data.n_val=1, data.n_test=10000000000: "
                                        "a scene of 10000000005 views of 8 x 8 pixels needs about "),
])
def test_the_commands_reading_a_run_back_check_its_overrides_as_nerfexp_does(saved_run, command, arguments, message):
    with pytest.raises(SystemExit) as exit:
        command.main([str(saved_run), *arguments])
    assert str(exit.value.code).startswith(message), exit.value.code


def test_a_run_of_an_earlier_nerfexp_with_a_key_no_rule_covers_is_still_read_back(saved_run):
    cfg = run_config(saved_run)
    with open_dict(cfg):
        cfg.scale.retired_setting = 3  # a key an earlier version wrote and this one no longer reads
    check_run_settings(cfg)  # the run's own key, not a user's mistake
    with pytest.raises(ConfigError, match="^scale.retired_setting=3: not a setting nerfexp reads"):
        check_settings(cfg)  # a new run's config is the user's: there it is a typo
    with open_dict(cfg):
        cfg.data.retired_setting = 3  # but an argument the scene's class no longer takes cannot build it
    with pytest.raises(ConfigError, match=r"^data.retired_setting: ProceduralScene takes no argument retired_setting "
                                          r"\(it takes n_train, n_val, background, "):
        check_run_settings(cfg)


def test_lpips_weights_are_looked_for_only_by_the_command_that_scores(saved_run, tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))  # an empty torch hub cache
    check_run_settings(run_config(saved_run, ["model.lpips=true"]))  # render, export, view: no LPIPS scored
    with pytest.raises(ConfigError, match="^model.lpips=true: no AlexNet ImageNet weights at "):
        run_settings(saved_run, ["model.lpips=true"])  # nerfexp-eval's


RUN_KEYS = ["model.chunk", "scale.chunk", "data.near", "data.far", "data.n_test", "scale.image_size",
            "data.supersample", "data.background", "sampler.n_coarse", "sampler.n_fine", "hierarchical",
            "seed", "model.renderer.field.density_noise_std", "trainer.precision"]
NUMBER_TEXTS = st.one_of(  # what a user may type as an argument: small, huge, not finite, not a number
    st.integers(-3, 40).map(str), st.integers(2 ** 40, 2 ** 80).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr), st.sampled_from(["nan", "inf", "5e-324", "abc", ""]))
RENDER_ARGUMENTS = ["--fps", "--frames", "--size", "--chunk", "--focus"]


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(command=st.sampled_from([evaluate, render]),
       changes=st.lists(st.tuples(st.sampled_from(RUN_KEYS), VALUES), max_size=3),
       arguments=st.lists(st.tuples(st.sampled_from(RENDER_ARGUMENTS), NUMBER_TEXTS), max_size=3))
def test_any_override_or_argument_of_a_command_reading_a_run_back_is_one_line_or_renders(saved_run, capsys, command,
                                                                                        changes, arguments):
    # argparse's own error (exit status 2), a NerfexpError's one line, or a finite render of what the command
    # renders: eval's first test view, render's first camera of its path (in process, without the video files)
    overrides = [override(key, value) for key, value in changes]
    flags = [word for flag, text in arguments for word in (flag, text)] if command is render else []
    parser = command.build_parser()
    try:
        args = parser.parse_args([str(saved_run), *overrides, *flags])
    except SystemExit as exit:
        assert exit.code == 2 and capsys.readouterr().err.splitlines()[-1].startswith(f"{parser.prog}: error: ")
        return
    try:
        if command is evaluate:
            cfg = run_settings(saved_run, args.overrides)
            module, _ = load_module(cfg, saved_run / LAST_CHECKPOINT)
            scene = instantiate(cfg.data)
            views = scene.views("test")
            frame = render_frame(module, scene, views.c2w[0], views.height, views.width, views.intrinsics[0])
        else:
            _, _, cfg, module, _ = load_run(args.run, args.overrides, args.chunk)
            scene = instantiate(cfg.data)
            cameras = training_path(scene, cfg.data, args.path, args.frames or 2, args.focus, args.fps or 30.0)
            height, width, lens = frame_size(cameras.height, cameras.width, cameras.intrinsics, args.size)
            frame = render_frame(module, scene, cameras.c2w[-1], height, width, lens)
    except NerfexpError as error:
        assert "\n" not in str(error), str(error)
        if isinstance(error, ConfigError) and "cannot apply" not in str(error):
            named = [key for key, _ in changes] + [flag for flag, _ in arguments]  # a key set or a flag given
            assert any(name in str(error) for name in named) or "which sets" in str(error), str(error)
        return
    assert all(torch.isfinite(image).all() for image in frame.values())


@pytest.mark.filterwarnings("ignore:.*supported for historical reasons")  # the aliases: 16, bf16, ...
def test_the_precisions_named_are_lightnings_own():
    # read from lightning.Trainer's public signature (its precision argument's literals): the list that
    # trainer.precision=bogus names; should Lightning's annotation change shape, the names would be lost
    import lightning as L

    names = lightning_precisions()
    assert {"32-true", "64-true", "16-mixed", "bf16-mixed", "32", "bf16"} <= set(names)
    for name in names:
        if not name.startswith("transformer-engine"):  # a package of its own
            L.Trainer(precision=name, accelerator="cpu", logger=False, enable_checkpointing=False)
    with pytest.raises(ValueError):
        L.Trainer(precision="bogus", accelerator="cpu", logger=False, enable_checkpointing=False)


def test_a_test_time_fit_is_estimated_where_it_has_rays_and_one_without_leaves_its_class_default(hydra_configs,
                                                                                                tmp_path):
    cfg = composed("appearance=embedding")
    del cfg.appearance.fit.rays  # a fit given without its rays: CodeFit's own 256, which fit
    check_settings(cfg)
    (tmp_path / RUN_CONFIG).parent.mkdir()
    OmegaConf.save(composed("appearance=embedding"), tmp_path / RUN_CONFIG)  # a run read back estimates it alike
    with pytest.raises(ConfigError, match=r"^appearance.fit.rays=1099511627776, scale.n_coarse=16 .*: a step of the "
                                          "test images' appearance fit of 1099511627776 rays"):
        check_run_settings(run_config(tmp_path, ["appearance.fit.rays=1099511627776"]))
