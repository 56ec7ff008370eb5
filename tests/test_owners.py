"""One owner per setting: every key a user sets under ``scale``, ``data``, ``encoding``, ``view_dependence``,
``acceleration``, the sampler (``hierarchical``, ``proposal``) and the components for real photographs
(``camera_opt``, ``appearance``, ``contraction``, ``test_cameras``) reaches what nerfexp builds (the model, the
data module, the trainer) under every option of every other group, or is refused in one line naming it.

Each key is overridden as the command line overrides it (after the groups are composed) with a value of its
domain that differs from the composed one; then either the built sections differ, or the settings check
refuses the override (``check_used``). A group that writes another group's key (``encoding=hashgrid`` writing
the optimizer's learning rate over ``scale.lr``) leaves ``scale.lr=X`` neither reaching nor refused.
"""

from importlib.resources import files

import pytest
from hydra import compose, initialize_config_module
from omegaconf import DictConfig, ListConfig, OmegaConf

from nerfexp.config_keys import leaves
from nerfexp.errors import ConfigError
from nerfexp.settings.checks import is_reference
from nerfexp.settings.schema import rule_of
from nerfexp.settings.unused import check_used, unused_reason

SECTIONS = ("scale", "data", "encoding", "view_dependence", "acceleration", "hierarchical", "proposal", "camera_opt",
            "appearance", "contraction", "test_cameras")
BUILT = ("model", "datamodule", "trainer")  # what the run builds from the config
GROUPS = ("encoding", "view_dependence", "data", "scale", "acceleration", "field", "optimizer", "camera_opt",
          "appearance", "contraction", "test_cameras")
ROOT = "data.root=/scene"  # the formats that read a folder need one to compose (nothing is read here)


def contexts() -> list[list[str]]:
    """Every option of every group, one group at a time (the others at their defaults), and every choice of the
    sampler; the formats that need a folder get one."""
    found = []
    for group in GROUPS:
        for option in sorted(p.name.removesuffix(".yaml") for p in (files("nerfexp.conf") / group).iterdir()
                             if p.name.endswith(".yaml")):
            found.append([f"{group}={option}", *([ROOT] if group == "data" and option != "procedural" else [])])
    return found + [[f"hierarchical={choice}"] for choice in ("true", "false", "proposal")]


def candidates(value) -> list:
    """Values to try in place of ``value``, of its kind."""
    if isinstance(value, bool):
        return [not value]
    if isinstance(value, int):
        return [value + 1, value - 1, value * 2, 1, 2, 3]
    if isinstance(value, float):
        return [value * 1.5 + 0.25, value / 2, value + 0.125, 0.5, 1e-3]
    if isinstance(value, str):
        return ["/sentinel/path", "black", "white", "relu", "trunc_exp", "sequential", "OPENCV", "sentinel"]
    if isinstance(value, list):
        if value and all(isinstance(v, int) and not isinstance(v, bool) for v in value):
            return [[v + 1 for v in value], value[:-1], value + [1]]
        if value and all(isinstance(v, float) for v in value):
            return [[min(v * 1.01, 0.999) for v in value]]
        return [[1], [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]]
    return [1, 2, 0.5, "/sentinel/path", [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], "sequential", [1]]  # null


def sentinel(cfg: DictConfig, key: str, value):
    """A value of ``key``'s domain other than ``value``, or None where there is none (a one-value domain)."""
    rule = rule_of(cfg, key)
    for candidate in candidates(value):
        if candidate != value and rule is not None and rule[1](candidate):
            return candidate
    return None


def built(cfg: DictConfig) -> dict:
    """The sections the run builds, resolved."""
    return {section: OmegaConf.to_container(cfg[section], resolve=True) for section in BUILT}


def user_keys(cfg: DictConfig) -> list[tuple[str, object]]:
    """The leaves a user sets in ``SECTIONS`` (class names and references to whole sections aside)."""
    return [(key, value) for key, value in leaves(cfg, skip=is_reference)
            if key.split(".")[0] in SECTIONS and not key.endswith(("._target_", "._partial_"))]


def raw(plain: dict, key: str):
    """The unresolved value at dotted ``key`` of the plain containers ``plain``."""
    for part in key.split("."):
        plain = plain[int(part)] if isinstance(plain, list) else plain[part]
    return plain


@pytest.fixture(scope="module")
def composed() -> dict[str, tuple[dict, dict]]:
    """Per context (its overrides, joined): the config as plain containers, nothing resolved (what only
    Hydra's runtime or training builds aside: the run directory, callbacks, logger), and the groups' options."""
    found = {}
    with initialize_config_module("nerfexp.conf", version_base=None):
        for context in contexts():
            cfg = compose("config", overrides=context, return_hydra_config=True)
            plain = OmegaConf.to_container(cfg, resolve=False)
            for key in ("hydra", "callbacks", "logger"):
                plain.pop(key)
            plain["trainer"].pop("default_root_dir")
            found[" ".join(context)] = (plain, dict(cfg.hydra.runtime.choices))
    return found


def test_every_key_reaches_what_is_built_or_is_refused_under_every_option_of_every_other_group(composed):
    checked, failures = 0, []
    for context, (plain, chosen) in composed.items():
        cfg = OmegaConf.create(plain)
        before = built(cfg)
        for key, value in user_keys(cfg):
            new = sentinel(cfg, key, value)
            if new is None:
                continue
            OmegaConf.update(cfg, key, new, merge=False)  # as the command line overrides it, after the groups
            reason = unused_reason(cfg, key, chosen)
            if reason is None and built(cfg) == before:
                failures.append(f"{context}: {key}={new} neither reaches {', '.join(BUILT)} nor is refused")
            OmegaConf.update(cfg, key, raw(plain, key), merge=False)
            checked += 1
    assert not failures, "\n".join(failures)
    assert checked > 900  # every key of every context was tried


def test_a_refused_override_is_one_line_naming_it():
    with initialize_config_module("nerfexp.conf", version_base=None):
        cfg = compose("config", overrides=["view_dependence=none", "scale.view_hidden=8"], return_hydra_config=True)
    with pytest.raises(ConfigError) as refused:
        check_used(cfg, ["scale.view_hidden=8"])
    assert str(refused.value) == ("scale.view_hidden=8: not used with view_dependence=none (view_dependence=mlp, ref "
                                  "read scale.view_hidden)")


def test_a_group_choice_chooses_options_but_never_writes_another_groups_keys():
    # encoding=hashgrid chooses Instant-NGP's field and optimizer; the command line still chooses others
    with initialize_config_module("nerfexp.conf", version_base=None):
        hashgrid = compose("config", overrides=["encoding=hashgrid"], return_hydra_config=True)
        paper_trunk = compose("config", overrides=["encoding=hashgrid", "field=nerf", "optimizer=adam",
                                                   "scale.lr=0.0125", "scale.depth=3"])
    assert (hashgrid.hydra.runtime.choices.field, hashgrid.hydra.runtime.choices.optimizer) == ("ngp", "ngp")
    assert (hashgrid.model.renderer.field.depth, hashgrid.model.optimizer.lr) == (1, 1e-2)
    assert (paper_trunk.model.renderer.field.depth, paper_trunk.model.optimizer.lr) == (3, 0.0125)
    assert paper_trunk.model.renderer.field.position_encoding._target_.endswith("HashGridEncoding")
    with pytest.raises(ConfigError, match=r"^scale.lr=0.123: not used with optimizer=ngp, which encoding=hashgrid "
                                          r"chooses \(optimizer=adam reads scale.lr\)$"):
        check_used(hashgrid, ["scale.lr=0.123"])


def test_the_scene_format_chooses_the_fields_training_noise_and_the_command_line_still_can():
    with initialize_config_module("nerfexp.conf", version_base=None):
        llff = compose("config", overrides=["data=llff", ROOT])
        quieter = compose("config", overrides=["data=llff", ROOT, "data.density_noise_std=0.25"])
        blender = compose("config", overrides=["data=blender", ROOT])
    assert llff.model.renderer.field.density_noise_std == 1.0  # the paper's, for real forward-facing scenes
    assert quieter.model.renderer.field.density_noise_std == 0.25
    assert blender.model.renderer.field.density_noise_std == 0.0
    assert isinstance(llff.model.renderer.field.skips, ListConfig)
