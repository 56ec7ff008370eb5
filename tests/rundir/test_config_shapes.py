"""A run read back is built only in the shapes nerfexp's own configs give its keys: a saved config whose key is
another shape (a section as a value or back, no class where one is built, another ``_partial_``, an argument a
class needs missing), and an argument of a command that reads a run back that changes a shape, are one line
naming the key, from every such command, before the checkpoint is read."""

import copy
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

import nerfexp.conf
from nerfexp.commands import evaluate, export, render, view
from nerfexp.errors import ConfigError
from nerfexp.rundir.config_shapes import SECTION, VALUE, Shape, own_keys, shapes
from nerfexp.rundir.layout import LAST_CHECKPOINT, RUN_CONFIG
from nerfexp.rundir.trained import run_config
from nerfexp.settings.components import argument_problem, components
from tests.helpers import TINY

COMMANDS = {"nerfexp-eval": evaluate.main, "nerfexp-render": render.main, "nerfexp-export": export.main,
            "nerfexp-view": view.main}
NEVER_READ = b"not a checkpoint: reading it is an error of its own"  # what every refusal below comes before
CONF = Path(nerfexp.conf.__file__).parent
OPTIONS = [(f"+{group.name}" if group.name == "sweeps" else group.name, option.stem)  # every option of every group
           for group in sorted(CONF.iterdir()) if group.is_dir() and group.name not in ("hydra", "__pycache__")
           for option in sorted(group.glob("*.yaml"))]


@pytest.fixture(scope="module")
def saved() -> dict:
    """A TINY run's saved config (composed, nothing resolved), as plain containers."""
    with initialize_config_module("nerfexp.conf", version_base=None):
        return OmegaConf.to_container(compose("config", overrides=list(TINY)), resolve=False)


def run_dir(folder: Path, config: dict) -> Path:
    """A run directory holding ``config`` as its saved config and a checkpoint file no command may read."""
    (folder / RUN_CONFIG).parent.mkdir(parents=True, exist_ok=True)
    (folder / RUN_CONFIG).write_text(yaml.safe_dump(config))
    (folder / LAST_CHECKPOINT).parent.mkdir(exist_ok=True)
    (folder / LAST_CHECKPOINT).write_bytes(NEVER_READ)
    return folder


def snapshot(folder: Path) -> dict:
    """Every file under ``folder``: its size and modification time, to show nothing was written."""
    return {p.relative_to(folder): (p.stat().st_size, p.stat().st_mtime_ns) for p in folder.rglob("*")}


def refusal(command: str, arguments: list[str], folder: Path, monkeypatch) -> str:
    """What ``command`` (in this process, in ``folder``) says, ending, with ``arguments``; nothing written."""
    monkeypatch.chdir(folder)
    before = snapshot(folder)
    with pytest.raises(SystemExit) as ended:
        COMMANDS[command](arguments)
    assert snapshot(folder) == before
    return str(ended.value.code)


# The shapes themselves, against what is written


def test_a_keys_shape_is_what_it_is_references_followed_and_lists_are_values():
    cfg = OmegaConf.create({"grid": {"_target_": "a.B", "_partial_": True, "size": [1, 2]}, "uses": "${grid}",
                            "none": None, "width": "${grid.size}", "plain": {"x": 1}, "lost": "${nowhere}"})
    found = shapes(cfg)
    assert found == {
        "grid": Shape(SECTION, "a.B", True), "grid._target_": Shape(VALUE), "grid._partial_": Shape(VALUE),
        "grid.size": Shape(VALUE), "none": Shape(VALUE), "plain": Shape(SECTION), "plain.x": Shape(VALUE),
        "uses": Shape(SECTION, "a.B", True), "uses._target_": Shape(VALUE), "uses._partial_": Shape(VALUE),
        "uses.size": Shape(VALUE), "width": Shape(VALUE)}  # "lost" leads nowhere: resolving the config names it
    # reached through a reference: after the keys written where they are, so that a key is named where it is set
    assert list(found)[-5:] == ["uses", "uses._target_", "uses._partial_", "uses.size", "width"]


def test_a_reference_into_a_section_on_its_way_ends_the_walk():
    cfg = OmegaConf.create({"a": {"x": "${b}"}, "b": {"y": "${a}"}})
    assert set(shapes(cfg)) >= {"a", "b", "a.x", "b.y"}  # no end of a.x.y.x...: refused where it is resolved


def test_nerfexps_own_shapes_are_read_from_its_files():
    own = own_keys()
    # the field is built by the renderer (partial); the sampler whole (sampler=paper's HierarchyChoice) or partial
    # (sampler=march's GridMarchSampler, which the renderer builds); a reference carries its section's shapes
    assert own["model.renderer.field"].partials == {True} and own["sampler"].partials == {False, True}
    assert own["sampler"].partials_of("nerfexp.nerf.hierarchy.HierarchyChoice") == {False}
    assert own["sampler"].partials_of("nerfexp.nerf.marching.GridMarchSampler") == {True}
    assert own["model.renderer.sampler"] == own["sampler"]
    assert own["scale.width"].kinds == {VALUE} and own["model.renderer.field.width"].kinds == {VALUE}
    assert own["acceleration.grid"].kinds == {VALUE, SECTION}  # null (none) or the occupancy grid
    # a file that sets a section's class alone (sweeps/sparse_tables.yaml's LazyAdam) says nothing of _partial_
    assert "nerfexp.training.optimizers.LazyAdam" in own["model.optimizer"].targets
    assert own["model.optimizer"].partials == {True}


@pytest.mark.parametrize(("group", "option"), OPTIONS)
def test_every_option_of_nerfexps_configs_reads_back_in_its_shapes(tmp_path, group, option):
    with initialize_config_module("nerfexp.conf", version_base=None):
        cfg = compose("config", overrides=[f"{group}={option}"])
    if OmegaConf.is_missing(cfg.data, "root"):
        cfg.data.root = "/x"  # where a scene read from files would be
    run_dir(tmp_path, OmegaConf.to_container(cfg, resolve=False))
    read_back = run_config(tmp_path)  # the shapes, the classes at their keys, the references
    assert [problem for component in components(read_back) if (problem := argument_problem(component))] == []


# A saved config in another shape: refused by every command that reads a run back


def put(config: dict, dotted: str, value) -> None:
    """Set (or, for ``DELETE``, remove) ``dotted`` in the plain containers ``config``."""
    *parents, leaf = dotted.split(".")
    for key in parents:
        config = config[key]
    if value is DELETE:
        del config[leaf]
    else:
        config[leaf] = value


DELETE = object()
SAVED_SHAPES = {  # (changes to a TINY run's saved config, the refusal after "FILE: " or "PROG: error: ")
    "a section as a value": ({"sampler": "evil"}, "{file}: sampler is a value where nerfexp's configs have a section"),
    "a section as a list": ({"model.renderer": [1, 2]},
                            "{file}: model.renderer is a value where nerfexp's configs have a section"),
    "a value as a section": ({"scale.width": {"a": 1}},
                             "{file}: scale.width is a section where nerfexp's configs have a value"),
    "_partial_ flipped": ({"model.renderer.field._partial_": False},
                          "{file}: model.renderer.field._partial_=false where nerfexp's configs have _partial_: true"),
    "_partial_ removed": ({"view_dependence._partial_": DELETE},
                          "{file}: view_dependence._partial_=false where nerfexp's configs have _partial_: true"),
    "_partial_ added": ({"sampler._partial_": True},
                        "{file}: sampler._partial_=true where nerfexp's configs have _partial_: false"),
    "_target_ removed": ({"sampler._target_": DELETE}, "{file}: sampler has no _target_ where nerfexp's configs "
                                                       "have one (nerfexp.nerf.hierarchy.HierarchyChoice, "
                                                       "nerfexp.nerf.marching.GridMarchSampler)"),
    "an argument missing": ({"sampler.n_coarse": DELETE}, "sampler: HierarchyChoice needs n_coarse (not given)"),
    "an argument of a partial missing": ({"view_dependence.direction_encoding": DELETE},
                                         "view_dependence: MLPViewDependence needs direction_encoding (not given)"),
    "an argument of the proposals missing": ({"hierarchical": "proposal", "proposal.n_samples": DELETE},
                                             "proposal: ProposalSampler needs n_samples (not given)"),
    "an argument no longer taken": ({"model.renderer.field.retired": 1},
                                    "model.renderer.field.retired: NeRFField takes no argument retired (it takes "
                                    "position_encoding, view_head, depth, width, skips, "),
}


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("case", SAVED_SHAPES)
def test_a_saved_config_in_another_shape_is_one_line_before_the_checkpoint_is_read(saved, tmp_path, monkeypatch,
                                                                                    command, case):
    changes, message = SAVED_SHAPES[case]
    config = copy.deepcopy(saved)
    for dotted, value in changes.items():
        put(config, dotted, value)
    folder = run_dir(tmp_path / "run", config)
    line = refusal(command, [str(folder)], tmp_path, monkeypatch)
    assert line.startswith(f"{command}: error: {message.format(file=folder / RUN_CONFIG)}"), line
    assert "\n" not in line


# An argument that changes a shape: refused by every command that reads a run back

OVERRIDE_SHAPES = {  # (the argument, the refusal after "cannot apply ARGUMENT to FILE: ")
    "a section as a value": ("sampler=evil", "sampler is a value where the run's config has a section"),
    "a referenced section as a value": ("model.renderer.sampler=7",
                                        "model.renderer.sampler is a value where the run's config has a section"),
    "a section as a list": ("model.renderer=[1,2]", "model.renderer is a value where the run's config has a section"),
    "a value as a section": ("scale.width={a: 1}", "scale.width is a section where the run's config has a value"),
    "a list as a section": ("scale.skips={a: 1}", "scale.skips is a section where the run's config has a value"),
    "null as a section": ("model.appearance_fit={_target_: nerfexp.nerf.appearance.CodeFit}",
                          "model.appearance_fit is a section where the run's config has a value"),
    "_partial_ flipped": ("model.renderer.field._partial_=false",
                          "model.renderer.field._partial_=false where the run's config has _partial_: true"),
}


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("case", OVERRIDE_SHAPES)
def test_an_argument_that_changes_a_shape_is_one_line_before_the_checkpoint_is_read(saved, tmp_path, monkeypatch,
                                                                                     command, case):
    argument, message = OVERRIDE_SHAPES[case]
    folder = run_dir(tmp_path / "run", saved)
    line = refusal(command, [str(folder), "data.n_test=1", argument], tmp_path, monkeypatch)
    assert line.startswith(f"{command}: error: cannot apply {argument} to {folder / RUN_CONFIG}: {message}: an "
                           "argument of a command that reads a run back changes values, never the shape"), line


@pytest.mark.parametrize("argument", ["data.n_test=1", "hierarchical=false", "scale.skips=[]", "data.near=null",
                                      "encoding.position._target_=nerfexp.nerf.encodings.PositionalEncoding"])
def test_an_argument_within_the_shapes_changes_the_value(saved, tmp_path, argument):
    key, _, value = argument.partition("=")
    cfg = run_config(run_dir(tmp_path, saved), [argument])
    assert OmegaConf.select(cfg, key) == yaml.safe_load(value)


def test_a_class_named_where_another_belongs_is_named_by_its_class_before_its_shape(saved, tmp_path):
    # the field (built partially) where the appearance fit (built whole) goes: the class is what is wrong
    config = copy.deepcopy(saved)
    config["model"]["appearance_fit"] = "${model.renderer.field}"
    with pytest.raises(ConfigError, match=r"model.appearance_fit._target_='nerfexp.nerf.fields.NeRFField' is not a "
                                          "class nerfexp builds at model.appearance_fit"):
        run_config(run_dir(tmp_path, config))
