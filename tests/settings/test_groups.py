"""A config group's value is one of its options, by name (nerfexp.settings.groups), for every group of nerfexp's
conf/: a list or a path, which Hydra composes and records as another choice (none, or the path), is refused in
one line naming the group, the value and its options, on the command line, in a composed config (a single run's,
a sweep's, a job's), and where a config file's defaults list gives it; every option of every group passes."""

from pathlib import Path

import pytest
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

import nerfexp.conf
from nerfexp.errors import ConfigError
from nerfexp.settings.checks import check_composition
from nerfexp.settings.groups import check_group_overrides, check_group_values, derived_choices, is_nerfexp_group
from tests.helpers import TINY, one_error_line, options_of, read_json, run_nerfexp, without_overrides

CONF = Path(nerfexp.conf.__file__).parent
EXPERIMENTS = options_of("experiment")
LIST = "; a list is not one (Hydra would compose each config it names and record no choice)"
PATH = "; a path is not one (Hydra would compose whatever config it leads to, in another group too)"
APPENDED = {"sweeps"}  # groups that config.yaml's defaults list does not hold: chosen by appending (+sweeps=)
# groups whose choice config.yaml's defaults list reads (${acceleration}_${encoding}): given a list, Hydra composes
# nothing at all (the interpolation finds no choice), and the command line's check refuses the list before that
READ_BY_DEFAULTS = {"acceleration", "encoding"}
NEEDS = {"encoding/hashgrid_sizes": ["encoding=hashgrid"]}  # what puts a nested group in the defaults list


def conf_groups() -> dict[str, list[str]]:
    """{group: its options} for every folder of nerfexp's conf/ that holds option files, read from the folders
    (nested ones by their path: encoding/hashgrid_sizes, hydra/launcher), but those config.yaml's defaults list
    chooses from other groups' choices (acceleration/by_encoding: no one chooses them)."""
    derived = set(derived_choices().values())
    return {group: sorted(p.stem for p in path.glob("*.yaml")) for path in sorted(CONF.rglob("*"))
            if path.is_dir() and any(path.glob("*.yaml"))
            and (group := path.relative_to(CONF).as_posix()) not in derived}


GROUPS = conf_groups()


def test_the_groups_are_every_folder_nerfexp_ships():
    assert {"ablation", "experiment", "scale", "sampler", "encoding/hashgrid_sizes", "hydra/launcher",
            "sweeps"} <= set(GROUPS)
    assert all(is_nerfexp_group(group) for group in GROUPS)


def bad_values(group: str) -> list[tuple[str, str]]:
    """(value, what the refusal adds) for ``group``: a list of its first option, and paths to it that stay in the
    group or leave it (to another group's option, and an absolute path)."""
    option = GROUPS[group][0]
    other = next(g for g in GROUPS if g != group and not g.startswith("hydra"))
    return [(f"[{option}]", LIST), (f"./{option}", PATH), (f"{option}/../{option}", PATH),
            (f"../{other}/{GROUPS[other][0]}", PATH), (f"/{other}/{GROUPS[other][0]}", PATH), ("..", PATH)]


@pytest.mark.parametrize("group", GROUPS)
def test_every_group_given_a_list_or_a_path_on_the_command_line_is_one_line(group):
    listed = "" if group.startswith("hydra/") else f" (choose from {', '.join(GROUPS[group])})"
    for prefix in ("", "+"):
        for value, reason in bad_values(group):
            for argument in (f"{prefix}{group}={value}", f"{prefix}{group}={GROUPS[group][0]},{value}"):  # a sweep
                with pytest.raises(ConfigError) as raised:
                    check_group_overrides(["-m", "seed=0,1", argument], is_nerfexp_group)
                assert str(raised.value) == f"{argument}: a config group takes an option's name{listed}{reason}"


@pytest.fixture(scope="module")
def hydra_configs():
    with initialize_config_module("nerfexp.conf", version_base=None):
        yield


def composed(*overrides: str):
    return compose("config", overrides=list(overrides), return_hydra_config=True)


@pytest.mark.parametrize("group", GROUPS)
def test_every_group_composed_from_a_path_is_refused_by_its_recorded_choice(hydra_configs, group):
    # Hydra composes ./OPTION from inside the group and records the path as the choice: refused by the override,
    # and by the choice alone, as a config file's defaults list would give it
    option = GROUPS[group][0]
    argument = f"{'+' if group in APPENDED else ''}{group}=./{option}"
    cfg = composed(*NEEDS.get(group, []), argument)
    assert cfg.hydra.runtime.choices[group] == f"./{option}"  # what a run would record without the check
    with pytest.raises(ConfigError) as raised:
        check_group_values(cfg.hydra)
    assert str(raised.value).startswith(f"{argument}: a config group takes an option's name (choose from ")
    assert str(raised.value).endswith(PATH)
    with pytest.raises(ConfigError) as raised:
        check_group_values(without_overrides(cfg).hydra)
    assert str(raised.value).startswith(f"{group}=./{option}: a config group takes an option's name")


@pytest.mark.parametrize("group", [g for g in GROUPS if g not in APPENDED | set(NEEDS) | READ_BY_DEFAULTS
                                   and not g.startswith("hydra")])
def test_every_group_composed_from_a_list_is_refused_though_hydra_records_no_choice(hydra_configs, group):
    option = GROUPS[group][0]
    cfg = composed(f"{group}=[{option}]")
    assert group not in cfg.hydra.runtime.choices  # what a run would record without the check: no choice
    with pytest.raises(ConfigError, match=r"^" + rf"{group}=\[{option}\]: a config group takes an option's name"):
        check_group_values(cfg.hydra)
    with pytest.raises(ConfigError) as raised:
        check_group_values(without_overrides(cfg).hydra)
    assert str(raised.value) == (f"{group}=[...] in a config's defaults list: a config group takes an option's name "
                                 f"(choose from {', '.join(GROUPS[group])}){LIST}")


def test_the_issues_cases_compose_another_variant_than_they_record(hydra_configs):
    # experiment=[fast] trains the preset and records no experiment; ../ablation/no_posenc trains the row as a preset
    listed = composed("experiment=[fast]")
    assert "experiment" not in listed.hydra.runtime.choices and listed.hierarchical is False
    row = composed("experiment=../ablation/no_posenc")
    assert row.hydra.runtime.choices["experiment"] == "../ablation/no_posenc"
    assert row.hydra.runtime.choices["ablation"] is None and row.hydra.runtime.choices["encoding"] == "none"
    for cfg, said in ((listed, "experiment=[fast]"), (row, "experiment=../ablation/no_posenc")):
        with pytest.raises(ConfigError, match=r"^" + said.replace("[", r"\[").replace("]", r"\]")):
            check_composition(cfg, cfg.hydra)


@pytest.mark.parametrize(("group", "option"), [(g, o) for g, options in GROUPS.items() for o in options])
def test_every_option_of_every_group_passes(hydra_configs, group, option):
    prefix = "+" if group in APPENDED else ""
    cfg = composed(*NEEDS.get(group, []), f"{prefix}{group}={option}", "++data.root=/x")
    check_composition(cfg, cfg.hydra)
    check_group_overrides([f"{prefix}{group}={option}"], is_nerfexp_group)


def test_removing_a_group_is_not_a_list(hydra_configs):
    cfg = composed("~experiment", "~ablation")
    check_group_values(cfg.hydra)
    check_group_values(composed("~experiment=fast", "experiment=fast").hydra)


def searched(tmp_path: Path, files: dict[str, str]) -> str:
    """A folder for ``hydra.searchpath`` holding ``files`` ({path: text}), and the override that adds it."""
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    return f"hydra.searchpath=[file://{tmp_path}]"


GLOBAL = "# @package _global_\n"


def test_an_option_on_the_search_path_is_one_and_a_config_files_defaults_are_checked(hydra_configs, tmp_path):
    search = searched(tmp_path, {
        "experiment/mine.yaml": GLOBAL + "scale:\n  steps: 7\n",  # a user's own preset: an option of experiment
        "experiment/pathy.yaml": GLOBAL + "defaults:\n  - override /scale: ./paper\n",
        "experiment/listy.yaml": GLOBAL + "defaults:\n  - override /scale: [paper]\n",
        "experiment/rowed.yaml": GLOBAL + "defaults:\n  - override /ablation: ../ablation/no_posenc\n",
    })
    mine = composed(search, "experiment=mine")
    check_composition(mine, mine.hydra)
    for option, message in (
            ("pathy", f"scale=./paper: a config group takes an option's name (choose from cpu, paper){PATH}"),
            ("listy", f"scale=[...] in a config's defaults list: a config group takes an option's name (choose from "
                      f"cpu, paper){LIST}"),
            ("rowed", "ablation=../ablation/no_posenc: a config group takes an option's name (choose from complete, ")):
        cfg = composed(search, f"experiment={option}")
        with pytest.raises(ConfigError) as raised:
            check_composition(cfg, cfg.hydra)
        assert str(raised.value).startswith(message)


def test_a_sweep_files_bad_choice_is_one_line_before_the_sweep_directory_is_made(tmp_path):
    search = searched(tmp_path / "configs", {
        "sweeps/pathy.yaml": GLOBAL + "defaults:\n  - override /experiment: ./fast\nhydra:\n  mode: MULTIRUN\n"})
    sweep = tmp_path / "sweep"
    result = run_nerfexp(search, "+sweeps=pathy", *TINY, f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert one_error_line(result) == ("nerfexp: error: experiment=./fast: a config group takes an option's name "
                                      f"(choose from {EXPERIMENTS}){PATH}")
    assert not sweep.exists()


def test_a_sweepers_bad_value_fails_its_job_in_one_line_before_any_work(tmp_path):
    # the sweeper's params are a job's own overrides: known only when the job starts
    search = searched(tmp_path / "configs", {
        "sweeps/params.yaml": GLOBAL + "hydra:\n  mode: MULTIRUN\n  sweeper:\n    params:\n      experiment: ./fast\n"})
    sweep = tmp_path / "sweep"
    result = run_nerfexp(search, "+sweeps=params", *TINY, f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    line = f"experiment=./fast: a config group takes an option's name (choose from {EXPERIMENTS}){PATH}"
    assert result.returncode == 1 and line in result.stderr
    status = read_json(sweep / "0" / "status.json")
    assert status["state"] == "failed" and status["error"] == f"ConfigError: {line}"
    assert not (sweep / "0" / "checkpoints").exists() and not (sweep / "0" / "metrics.jsonl").exists()
    assert "experiment=./fast" in OmegaConf.load(sweep / "0" / ".hydra" / "overrides.yaml")  # the job's own
