"""The settings package is generic (issue 53): it names no component's key, and a component brings its own rules
(``CONSISTENT``, ``MEMORY``, ...: ``nerfexp.domains``) that the settings check asks without a central edit."""

import ast
import re
from collections.abc import Callable
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module
from hydra.utils import get_class
from omegaconf import OmegaConf

import nerfexp.conf
import nerfexp.settings
from nerfexp.config_keys import entries, reference
from nerfexp.errors import ConfigError
from nerfexp.memory import machine_bytes
from nerfexp.settings import components as components_module
from nerfexp.settings.checks import check_settings
from nerfexp.settings.components import components, walked_once
from tests.components.toy import PowerEncoding
from tests.helpers import TINY

CONF = Path(nerfexp.conf.__file__).parent
REPO = Path(__file__).parents[2]
SEARCH = f"hydra.searchpath=[file://{REPO / 'tests' / 'components'}]"  # where encoding/toy.yaml lies
PACKAGE = re.compile(r"^# @package (\S+)", re.MULTILINE)
DOTTED = re.compile(r"\.?[A-Za-z_]\w*(?:\.[A-Za-z_]\w*)+|\.[A-Za-z_]\w*")  # a.b.c, or an f-string's piece .c


def conf_components() -> tuple[set[str], set[str], set[str]]:
    """From every option file of nerfexp's conf/ (read as YAML): the argument names the classes its ``_target_``s
    name declare in ``DOMAINS``; the dotted keys where such a component sits in a composed config (its file's
    package, and the keys that interpolate one: ``model.renderer.field.position_encoding``); the top-level keys and
    groups."""
    names, locations, references, top = set(), set(), {}, set()
    for path in CONF.rglob("*.yaml"):
        group = path.parent.relative_to(CONF).as_posix()
        if group.startswith("hydra"):
            continue
        top.add(group.split("/")[0])
        header = PACKAGE.search(path.read_text())
        package = header.group(1) if header else group.replace("/", ".")
        prefix = "" if package in ("_global_", ".") else f"{package}."
        content = OmegaConf.to_container(OmegaConf.load(path), resolve=False) or {}
        top |= set(content) if not prefix else set()
        for key, value in [("", content), *entries(content)]:
            key = f"{prefix}{key}".rstrip(".")
            if isinstance(value, dict) and isinstance(value.get("_target_"), str):
                try:
                    declared = getattr(get_class(value["_target_"]), "DOMAINS", {})
                except (ImportError, ValueError):
                    continue
                if declared:
                    names |= set(declared)
                    locations.add(key)
            elif reference(value) is not None:
                references[key] = reference(value)
    locations |= {key for key, named in references.items() if named in locations}
    return names, locations, top - {""}


def quoted_keys(source: str) -> list[str]:
    """The component keys ``source`` quotes: a string (or an f-string's text between its fields) that is a word,
    and every dotted key within a string; docstrings aside (they may say, in words, what a component declares)."""
    tree = ast.parse(source)
    docstrings = {id(node.body[0].value) for node in ast.walk(tree)
                  if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef) and node.body
                  and isinstance(node.body[0], ast.Expr) and isinstance(node.body[0].value, ast.Constant)}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings:
            text = node.value
            found += [text] if re.fullmatch(r"[A-Za-z_]\w*", text) else []
            found += DOTTED.findall(text)
    return found


def component_keys(quoted: list[str], names: set[str], locations: set[str], allowed: set[str]) -> list[str]:
    """Those of ``quoted`` that name a component's argument: a word among ``names`` (not ``allowed``, the top-level
    keys: ``hierarchical`` is the renderer's argument and the command line's key), a dotted key whose section is
    one of ``locations`` and whose last part is among ``names``, or an f-string's piece ``.NAME``."""
    def names_one(key: str) -> bool:
        section, _, last = key.rpartition(".")
        if last not in names:
            return False
        return section in locations if section else key.startswith(".") or key not in allowed
    return [key for key in quoted if names_one(key)]


def test_the_settings_package_names_no_component_key():
    names, locations, allowed = conf_components()
    assert {"n_freqs", "log2_table_size", "coarsest", "width", "skips", "image_size", "resolution", "dim"} <= names
    assert {"encoding.position", "model.renderer.field", "data", "acceleration.grid", "view_dependence",
            "model.renderer.field.position_encoding"} <= locations
    assert {"seed", "hierarchical", "data", "scale"} <= allowed
    # the rule catches what it is for (the central checks before issue 53 named these)
    assert sorted(component_keys(quoted_keys('x = "n_freqs" in cfg\ny = f"{key}.rays"\nz = "model.renderer.field.width"'
                                             '\nw = "a and data.ndc=true"'), names, locations, allowed)) \
        == [".rays", "data.ndc", "model.renderer.field.width", "n_freqs"]
    assert component_keys(quoted_keys('x = "scale.width"\ny = "hierarchical"\nz = f"{n} rays x {m} samples"'),
                          names, locations, allowed) == []
    named = {path.name: component_keys(quoted_keys(path.read_text()), names, locations, allowed)
             for path in Path(nerfexp.settings.__file__).parent.glob("*.py")}
    assert not any(named.values()), f"settings/ names component keys: {named}"


def test_the_settings_package_names_no_size_of_the_scale():
    # a scale key has the rules of the keys it lands in (nerfexp.settings.schema.readers_rule): none is listed
    # centrally, so that a component sized by a new scale.KEY edits nothing of nerfexp (tests/test_developing.py)
    named = {path.name: [key for key in quoted_keys(path.read_text()) if key.startswith("scale.")]
             for path in Path(nerfexp.settings.__file__).parent.glob("*.py")}
    assert not any(named.values()), f"settings/ names scale keys: {named}"
    assert quoted_keys('SCHEMA = {"scale.steps": COUNT}') == ["scale.steps"]  # what it would find


@pytest.fixture(scope="module")
def hydra_configs():
    with initialize_config_module("nerfexp.conf", version_base=None):
        yield


def toy(*overrides):
    return compose("config", overrides=[*TINY, "encoding=toy", SEARCH, "trainer.default_root_dir=.", *overrides])


def test_a_new_component_brings_its_own_rules(hydra_configs):
    # tests/components/toy.py declares CONSISTENT and MEMORY; nothing in nerfexp names the toy or its keys
    assert "encoding.position" in [c.key for c in components(toy())]
    check_settings(toy())
    with pytest.raises(ConfigError) as refused:
        check_settings(toy("encoding.position.gain=2", "encoding.position.n_powers=9"))
    assert str(refused.value) == ("encoding.position.n_powers=9, encoding.position.gain=2: expected "
                                  f"{PowerEncoding.TOP_POWER} powers at most with a gain above 1")
    # 2^40 powers x 4 bytes = 4 TiB of exponents
    powers = 2 ** 40
    assert 4 * powers > machine_bytes()
    with pytest.raises(ConfigError) as refused:
        check_settings(toy(f"encoding.position.n_powers={powers}"))
    assert str(refused.value).startswith(f"encoding.position.n_powers={powers}: the exponents of {powers} powers "
                                         "needs about 4 TiB of memory")


def test_a_component_that_is_not_built_is_not_asked(hydra_configs):
    # the proposal networks are built only with hierarchical=proposal (the renderer's APPLIES): their skips
    # past their depth are refused there alone
    assert "proposal.network" not in [c.key for c in components(toy())]
    check_settings(toy("proposal.network.skips=[5]"))
    with pytest.raises(ConfigError, match=r"^proposal.network.skips=\[5\], proposal.network.depth=2: expected"):
        check_settings(toy("hierarchical=proposal", "proposal.network.skips=[5]"))


def test_a_config_held_is_walked_once_and_a_hold_within_a_hold_keeps_the_outer_walk(hydra_configs, monkeypatch):
    cfg = toy()
    fresh = [(c.key, c.cls) for c in components(cfg)]
    walks = []
    walk = components_module.walk
    monkeypatch.setattr(components_module, "walk", lambda config: walks.append(config) or walk(config))
    with walked_once(cfg):
        first = [(c.key, c.cls) for c in components(cfg)]
        with walked_once(cfg):  # as unused_settings would be, called inside a check holding the same config
            inner = [(c.key, c.cls) for c in components(cfg)]
        after = [(c.key, c.cls) for c in components(cfg)]
        assert len(walks) == 1
        other = toy("hierarchical=proposal")  # another config is walked as it is, each time
        assert [c.key for c in components(other)] == [c.key for c in components(other)]
        assert len(walks) == 3
    assert first == inner == after == fresh
    assert [(c.key, c.cls) for c in components(cfg)] == fresh and len(walks) == 4  # outside: walked anew


# A component's rules read the arguments it is built with; what builds a partial passes what its annotation says


class Built:
    """A component of two arguments, one with a default."""

    def __init__(self, needed: int, optional: float = 0.5):
        self.needed, self.optional = needed, optional


def test_a_rule_reads_an_argument_not_given_as_its_default_and_one_it_needs_as_a_refusal():
    config = components_module.Arguments({"optional": 2.0}, "somewhere.built", Built)
    assert "needed" not in config and list(config) == ["optional"]  # what the config gives, as it gives it
    assert config["optional"] == 2.0 and components_module.Arguments({}, "k", Built)["optional"] == 0.5
    with pytest.raises(ConfigError, match=r"^somewhere.built: Built needs needed \(not given\)$"):
        config["needed"]


class Taker:
    def __init__(self, one: Callable[[int], Built], none: Callable[[], Built] | None, two: Callable[[int, str], Built],
                 any_: Callable[..., Built], built: Built, plain):
        pass


@pytest.mark.parametrize(("argument", "passed"), [("one", 1), ("none", 0), ("two", 2), ("any_", None),
                                                  ("built", None), ("plain", None), ("absent", None)])
def test_what_builds_a_partial_passes_is_what_its_annotation_says(argument, passed):
    assert components_module.passed_by(Taker, argument) == passed
    assert components_module.passed_by(None, argument) is None


def test_nerfexps_own_takers_say_what_they_pass(hydra_configs):
    # the field builds its colour head with its width; the renderer builds its sampler and fields with nothing more
    passed = {c.key: c.passed for c in components(toy("hierarchical=proposal"))}
    assert passed["view_dependence"] == 1 and passed["model.renderer.field"] == 0 and passed["proposal"] == 0
    assert passed["model.renderer"] == 0 and passed["sampler"] == 0  # built whole, by Hydra


@pytest.mark.parametrize(("override", "problem"), [
    ("~view_dependence.direction_encoding", "view_dependence: MLPViewDependence needs direction_encoding (not given)"),
    ("+model.renderer.field.retired=1", "model.renderer.field.retired: NeRFField takes no argument retired (it takes "
                                        "position_encoding, view_head, depth, width, skips, density_activation, "
                                        "density_bias, density_noise_std, appearance_dim)"),
    ("~sampler.n_single", "sampler: HierarchyChoice needs n_single (not given)"),
])
def test_a_component_whose_config_does_not_fit_its_class_is_named(hydra_configs, override, problem):
    found = [p for c in components(toy(override)) if (p := components_module.argument_problem(c)) is not None]
    assert found == [problem]
    assert [c for c in components(toy()) if components_module.argument_problem(c) is not None] == []
