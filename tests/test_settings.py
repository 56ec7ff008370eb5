"""The settings schema (nerfexp.settings): every key of every group option has a rule, values across and
beyond each domain are refused in one ConfigError naming the key or build, and unused overrides are named."""

import math

import pytest
from hydra import compose, initialize_config_module
from hydra.utils import instantiate
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf

from nerfexp.errors import ConfigError
from nerfexp.settings.checks import check_settings, checked_settings
from nerfexp.settings.schema import SCHEMA, matching
from nerfexp.settings.unused import unused_settings
from nerfexp.training.precision import fill_precision
from tests.helpers import TINY

GROUPS = {  # every option of every group (conf/), and the sweeps' configs
    "encoding": ["hashgrid", "none", "posenc"], "view_dependence": ["mlp", "none", "ref", "sh"],
    "data": ["blender", "colmap", "llff", "procedural"], "scale": ["cpu", "paper"],
    "trainer": ["bf16", "ddp", "default", "slurm"], "acceleration": ["none", "occupancy"],
    "callbacks": ["default"], "logger": ["csv", "mlflow", "none", "tensorboard", "wandb"],
    "ablation": ["complete", "far_fewer_images", "fewer_frequencies", "fewer_images", "more_frequencies",
                 "no_hierarchical", "no_pe_vd_h", "no_posenc", "no_view_dependence"],
    "+sweeps": ["components", "cpu_ablation", "paper_ablation", "smoke", "successors"],
}


@pytest.fixture(scope="module")
def hydra_configs():
    with initialize_config_module("nerfexp.conf", version_base=None):
        yield


def test_every_key_of_every_option_has_a_rule(hydra_configs):
    for group, options in GROUPS.items():
        for option in options:
            cfg = compose("config", overrides=[f"{group}={option}", "++data.root=/x"])  # the folder scenes need
            uncovered = [key for key, _ in checked_settings(cfg) if matching(SCHEMA, key) is None]
            assert not uncovered, f"{group}={option}: keys with no rule in nerfexp.settings.schema.SCHEMA: {uncovered}"


def composed(*overrides):
    """The TINY config with ``overrides``, as a job sees it but without Hydra's runtime (a test's cwd)."""
    return compose("config", overrides=[*TINY, *overrides, "trainer.default_root_dir=."])


@pytest.mark.parametrize(("overrides", "message"), [
    (["seed=abc"], "seed=abc: expected a whole number in [0, 4294967295]"),
    (["seed=-1"], "seed=-1: expected a whole number in [0, 4294967295]"),
    (["trainer.precision=bogus"], "trainer.precision=bogus: expected one of "),
    (["view_dependence=sh", "view_dependence.degree=7"], "view_dependence.degree=7: expected a whole number in [0, 3]"),
    (["scale.image_size=0"], "scale.image_size=0 (which sets data.image_size): expected a whole number >= 1"),
    (["scale.lr=nan"], "scale.lr=nan (which sets model.optimizer.lr): expected a finite number > 0"),
    (["callbacks.guard.on_nonfinite=ignore"], "callbacks.guard.on_nonfinite=ignore: expected one of stop, skip"),
    (["data.background=grey"], "data.background=grey (which sets model.renderer.background): expected one of "),
    (["data.aabb=[[0,0,0],[1,1]]"], "data.aabb=[[0, 0, 0], [1, 1]]: expected [[x0, y0, z0]"),
    (["hierarchical=maybe"], "hierarchical=maybe: expected one of true, false, proposal"),
    (["hierarchical=1"], "hierarchical=1: expected one of true, false, proposal"),
    (["hierarchical=proposal", "proposal.n_samples=[]"], "proposal.n_samples=[]: expected a non-empty list of "),
    (["hierarchical=proposal", "proposal.interlevel_weight=0"], "proposal.interlevel_weight=0: expected a finite "
                                                                "number > 0"),
    (["scale.skips=[5]"], "scale.skips=[5] (which sets model.renderer.field.skips): layer indices must be in 1..1"),
    (["hierarchical=proposal", "proposal.network.skips=[2]"], "proposal.network.skips=[2]: layer indices must be "
                                                              "in 1..1 for depth 2"),
    (["+foo=1"], "foo=1: not a setting nerfexp reads"),
    (["scale.lr=???"], "missing mandatory value: scale.lr (set it"),  # not model.optimizer.lr, which reads it
    (["data.near=5", "data.far=2"], "data.near=5 (which sets model.renderer.near) and data.far=2 (which sets "
                                    "model.renderer.far): expected near < far"),
    (["data.near=2", "data.far=2"], "data.near=2 (which sets model.renderer.near) and data.far=2"),
    (["scale.image_size=100000"], "scale.image_size=100000 (which sets data.image_size): a scene of 15 views needs "),
    (["scale.batch_rays=100000000"], "scale.batch_rays=100000000 (which sets datamodule.batch_rays): a training "
                                     "batch of 100000000 rays x 48 samples needs about"),
    (["encoding=hashgrid", "scale.hash_log2_table_size=40"], "scale.hash_log2_table_size=40 (which sets "
                                                             "encoding.position.log2_table_size): hash tables"),
])
def test_a_value_out_of_its_domain_is_one_error_naming_the_key(hydra_configs, overrides, message):
    with pytest.raises(ConfigError) as error:
        check_settings(composed(*overrides))
    assert str(error.value).startswith(message), str(error.value)


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
    assert [reason for _, reason in unused_settings(composed(), ["proposal.n_final=16"])] == [
        "hierarchical=true (a coarse network of model.renderer.n_coarse samples and a fine one of n_coarse + n_fine; "
        "set scale.n_coarse and scale.n_fine)"]


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


VALUES = st.one_of(  # across and beyond the domains: wrong types, negatives, zero, nan, huge, strings
    st.integers(-3, 5), st.integers(2 ** 31, 2 ** 64), st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(), st.sampled_from(["abc", "", "null", "stop", "skip", "white", "32-true", "auto"]),
)
KEYS = ["seed", "hierarchical", "scale.lr", "scale.batch_rays", "scale.depth", "scale.width", "scale.n_coarse",
        "scale.n_fine", "scale.chunk", "scale.image_size", "scale.position_input_scale", "scale.lr_warmup_steps",
        "data.n_train", "data.n_val", "data.supersample", "data.near", "data.far", "data.background",
        "encoding.position.n_freqs", "encoding.direction.n_freqs", "view_dependence.hidden",
        "callbacks.guard.on_nonfinite", "callbacks.guard.max_skips", "trainer.precision", "trainer.max_steps",
        "model.renderer.field.density_bias", "model.optimizer.eps", "model.lpips"]


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
