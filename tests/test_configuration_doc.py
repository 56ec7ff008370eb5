"""docs/configuration.md against the config tree it documents, read from conf/ itself, both ways, so that the page
cannot go stale. The page is written by hand: what a group or a key is for, and where to read more, are sentences
a person writes. What can go stale (the names and the values) is checked here against the files.

The page names what conf/ has:
- every group (each folder of conf/ holding options, nested ones by their path: ``encoding/hashgrid_sizes``), in
  its groups table with its default option (``config.yaml``'s defaults list), and under a heading of its own;
- every option of a group, in the first column of its section's option table (a table whose first header is
  "option"), and no other there;
- every key a user sets: each value an option's file writes (or ``config.yaml`` does, Hydra's own section
  aside), at the option's package, unless it is a reference to another key (``${scale.lr}``: that key is
  named) or a class (``_target_``, ``_partial_``), and only an option's own keys (those under its package; a
  global option's, under its group's name: a row, a preset or a sweep sets other groups' keys, which are theirs).

And it names nothing conf/ lacks: each dotted key in a code span under a group's name or a top-level key is one
some file writes (``hydra.*`` aside: Hydra's own keys are Hydra's); each ``GROUP=OPTION`` names an option of the
group (Hydra's own groups aside, whose options are Hydra's plugins' too; ``+sweeps=NAME``, in capitals, stands
for any); each value in a key table's "default"
column is that key's value in one of the files (or the key that value refers to), and in a column headed by an
option (``scale``'s ``cpu``, ``paper``) that option's value.
"""

import json
import os
import re

import pytest
import yaml
from omegaconf import OmegaConf

from nerfexp.config_keys import entries, leaves
from nerfexp.rundir.config_shapes import package
from nerfexp.settings.groups import default_choices
from tests.command_lines import refusal
from tests.helpers import REPO
from tests.markdown import command_lines, long_cells, names, section, spans, tables

CONF = REPO / "conf"
PAGE = (REPO / "docs" / "configuration.md").read_text()
CLASS_KEYS = ("_target_", "_partial_")
HYDRA = "hydra"  # Hydra's own section and groups: its keys and options are Hydra's and its plugins' too
GROUP_VALUE = re.compile(r"(?<![\w./])\+?(\w+(?:/\w+)*)=([\w,]+)")


def groups() -> dict[str, list[str]]:
    """{each group of conf/ (its folder's path, sweeps/ through its link): its options, the folder's YAML files}."""
    found = {}
    for folder, _, files in os.walk(CONF, followlinks=True):
        options = sorted(name.removesuffix(".yaml") for name in files if name.endswith(".yaml"))
        group = os.path.relpath(folder, CONF).replace(os.sep, "/")
        if options and group != ".":
            found[group] = options
    return found


GROUPS = groups()
TOP = "config.yaml"


def option_files() -> list[tuple[str, str]]:
    """(group, option) for every option's file of conf/, and ("", ``TOP``) for conf/config.yaml."""
    return [("", TOP), *[(group, option) for group, options in GROUPS.items() for option in options]]


def written(group: str, option: str) -> tuple[str, dict]:
    """The package of ``group``'s ``option`` (where Hydra puts its keys; "" the top) and its keys as written, its
    defaults list left out."""
    path = CONF / TOP if not group else CONF / group / f"{option}.yaml"
    text = path.read_text()
    content = yaml.safe_load(text) or {}
    content.pop("defaults", None)
    return package(text, group), content


def values() -> dict[str, dict[tuple[str, str], object]]:
    """{each dotted key a file of conf/ writes, sections too: {(group, option): its value there, as written}}."""
    found: dict[str, dict] = {}
    for group, option in option_files():
        prefix, content = written(group, option)
        for key, value in [*([(prefix, content)] if prefix else []), *entries(content, prefix)]:
            found.setdefault(key, {})[group, option] = value
    return found


VALUES = values()


def user_keys() -> dict[str, list[str]]:
    """{each key a user sets (the module's docstring): the files that write it}."""
    found: dict[str, list[str]] = {}

    def not_set_by_users(key: str, raw: object) -> bool:
        return key.rsplit(".", 1)[-1] in CLASS_KEYS or isinstance(raw, str) and "${" in raw

    for group, option in option_files():
        prefix, content = written(group, option)
        own = prefix or group.replace("/", ".")  # a global option's own keys: under its group's name
        start = f"{prefix}." if prefix else ""
        for key, _ in leaves(OmegaConf.create(content), not_set_by_users, start):
            if not own or key == own or key.startswith(f"{own}."):
                found.setdefault(key, []).append(f"{group}/{option}.yaml" if group else TOP)
    return found


def named_with_prefixes(text: str) -> set[str]:
    """The names ``text``'s code spans hold, and every dotted name's prefixes (``a.b.c`` names ``a.b`` and ``a``:
    a section is named where a key in it is)."""
    found = set()
    for name in names(text):
        parts = name.split(".")
        found |= {".".join(parts[:i]) for i in range(1, len(parts) + 1)}
    return found


def rows_of(text: str, first_header: str) -> list[tuple[list[str], list[str]]]:
    """(the header, a row) of each row of the tables of ``text`` whose first header is ``first_header``."""
    return [(table[0], row) for table in tables(text) if table[0][0] == first_header for row in table[1:]]


def same(a: object, b: object) -> bool:
    """Whether two values are the same YAML value, type and all (``true`` is not ``1``, ``4.0`` not ``4``)."""
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def is_value_of(shown: str, value: object) -> bool:
    """Whether the code span ``shown`` writes ``value``: the same YAML value, or the key ``value`` refers to
    (``scale.lr`` for ``${scale.lr}``)."""
    return same(yaml.safe_load(shown), value) or value == f"${{{shown}}}"


def test_the_tree_is_read_whole():
    assert {"encoding", "encoding/hashgrid_sizes", "sweeps", "hydra/launcher", "ablation"} <= set(GROUPS)
    assert GROUPS["scale"] == ["cpu", "paper"] and "paper_ablation" in GROUPS["sweeps"]
    keys = user_keys()
    assert keys["scale.lr"] == ["scale/cpu.yaml", "scale/paper.yaml"]  # each option's own keys
    assert keys["model.renderer.field.density_bias"] == ["field/nerf.yaml", "field/ngp.yaml"]  # at its package
    assert keys["encoding.position.finest"] == [f"encoding/hashgrid_sizes/{scale}.yaml" for scale in ("cpu", "paper")]
    assert keys["seed"] == [TOP] and "proposal.n_final" in keys
    assert "data.max_side" not in keys  # ${scale.max_side}: scale.max_side is the key a user sets
    assert "model.optimizer.lr" in keys and "model.optimizer._target_" not in keys  # ngp's own value; a class
    assert "data.n_train" in keys and not [key for key, files in keys.items() if "ablation/" in str(files)]
    assert "hydra.run.dir" not in keys and "hydra.launcher.partition" in keys  # Hydra's section; nerfexp's launcher


def test_the_readers_find_what_a_page_says():
    text = ("## The groups\n| group | default |\n|---|---|\n| `a` | `b` |\n\n### `x`\n| option | what |\n|---|---|\n"
            "| `o` (default) | `data.root=/d`, `encoding=none,posenc` |\n### `y`\nnot x's\n")
    assert rows_of(text, "option") == [(["option", "what"],
                                        ["`o` (default)", "`data.root=/d`, `encoding=none,posenc`"])]
    assert section(text, "`x`").strip().endswith("posenc` |") and section(text, "`z`") == ""
    assert {"data.root", "data", "encoding", "none", "posenc", "o"} <= named_with_prefixes(text)
    assert "d" not in named_with_prefixes(text)  # in a path
    assert GROUP_VALUE.findall("`nerfexp -m encoding=none,posenc data.root=/x +sweeps=smoke`") == [
        ("encoding", "none,posenc"), ("sweeps", "smoke")]
    assert is_value_of("1.0e-4", 0.0001) and is_value_of("scale.lr", "${scale.lr}") and not is_value_of("1", True)


@pytest.mark.parametrize("group", GROUPS)
def test_every_group_has_a_section_listing_its_options_and_none_else(group):
    text = section(PAGE, f"`{group}`")
    assert text, f"no heading `{group}`"
    listed = [spans(row[0])[0] for _, row in rows_of(text, "option")]
    assert sorted(listed) == GROUPS[group]


def test_every_group_is_in_the_groups_table_with_its_default_option():
    rows = {spans(row[0])[0]: spans(row[1]) for _, row in rows_of(section(PAGE, "The groups"), "group")}
    assert sorted(rows) == sorted(GROUPS)
    assert {group: shown for group, shown in rows.items() if shown} == {
        group: [option] for group, option in default_choices().items() if option is not None}


def test_every_key_a_user_sets_is_named():
    named = named_with_prefixes(PAGE)
    assert not {key: files for key, files in user_keys().items() if key not in named}


def test_every_key_named_is_one_the_config_writes():
    roots = {group.split("/")[0] for group in GROUPS} | set(yaml.safe_load((CONF / TOP).read_text()))
    dotted = {name for name in names(PAGE) if "." in name and name.split(".")[0] in roots - {HYDRA}}
    assert dotted and not dotted - set(VALUES)


def test_every_option_named_is_one_of_its_groups():
    pairs = [pair for span in spans(PAGE) for pair in GROUP_VALUE.findall(span)]
    assert pairs
    wrong = [f"{group}={option}" for group, chosen in pairs if group in GROUPS and not group.startswith(HYDRA)
             for option in chosen.split(",") if option not in GROUPS[group] and not option.isupper()]  # NAME: any
    assert not wrong


def test_every_default_shown_is_the_keys_value():
    wrong = []
    for title in ["Top-level keys", *[f"`{group}`" for group in GROUPS]]:
        group = title.strip("`") if title.startswith("`") else ""
        for header, row in rows_of(section(PAGE, title), "key"):
            (key,) = spans(row[0])
            for column, cell in zip(header[1:], row[1:], strict=True):
                option = column.strip("`")
                if column == "default":
                    written_at = list(VALUES.get(key, {}).values())
                elif option in GROUPS.get(group, []):
                    written_at = [VALUES.get(key, {}).get((group, option))]
                else:
                    continue
                wrong += [f"{key}: {shown} ({column})" for shown in spans(cell)
                          if not any(is_value_of(shown, value) for value in written_at)]
    assert not wrong


def test_its_cells_are_short():
    assert not long_cells(PAGE)


@pytest.mark.parametrize("command", command_lines(PAGE, {"nerfexp"}), ids=" ".join)
def test_every_example_is_a_command_line_nerfexp_takes(command):
    assert refusal(command) is None
