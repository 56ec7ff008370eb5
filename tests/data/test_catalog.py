"""Scenes by name (nerfexp.data.catalog): nerfexp's entries as their sources publish them, a user's catalogue read
key by key with one line per mistake naming the file, the entry and the key, and a mirror that replaces each
address's scheme and host."""

import pytest
import yaml

from nerfexp.data.catalog import (
    catalog_entries,
    find_entry,
    folder_formats,
    format_target,
    read_catalog,
    scene_problem,
    shipped,
)
from nerfexp.downloads import MIRROR, is_web_address, mirrored
from nerfexp.errors import ConfigError

BLENDER = "chair drums ficus hotdog lego materials mic ship".split()  # the paper's 8 synthetic scenes
LLFF = "fern flower fortress horns leaves orchids room trex".split()  # and its 8 forward-facing ones
MIPNERF360 = {"360_v2.zip": "bicycle bonsai counter garden kitchen room stump".split(),
              "360_extra_scenes.zip": ["flowers", "treehill"]}
GDRIVE = "https://drive.usercontent.google.com/download?id={}&export=download&confirm=t"
FOX_COMMIT = "abe236ee00cf90cfca6e36e65c00435d5b21f50a"
ENTRY = {"name": "mylab/chair", "format": "blender", "url": "https://host/chair.zip", "sha256": "ab" * 32,
         "path": "chair"}


def test_nerfexps_entries_are_the_scenes_researchers_use_as_their_sources_publish_them():
    entries = {entry.name: entry for entry in shipped()}
    expected = {f"blender/{s}": ("blender", GDRIVE.format("18JxhpWD-4ZmuFKLzKlAw-w5PpzZxXOcG"),
                                 "f01fd1b4ab045b0d453917346f26f898657bb5bec4834b95fdad1f361826e45e",
                                 f"nerf_synthetic/{s}") for s in BLENDER}
    expected |= {f"llff/{s}": ("llff", GDRIVE.format("16VnMcF1KJYxN9QId6TClMsZRahHNMW5g"),
                               "5794b432feaf4f25bcd603addc6ad0270cec588fed6a364b7952001f07466635",
                               f"nerf_llff_data/{s}") for s in LLFF}
    expected |= {f"mipnerf360/{s}": ("colmap", f"https://storage.googleapis.com/gresearch/refraw360/{archive}", None, s)
                 for archive, scenes in MIPNERF360.items() for s in scenes}
    expected["instant-ngp/fox"] = ("nerfstudio", f"https://github.com/NVlabs/instant-ngp/archive/{FOX_COMMIT}.zip",
                                   None, f"instant-ngp-{FOX_COMMIT}/data/nerf/fox")
    assert {name: (e.format, *e.urls, e.sha256, e.path) for name, e in entries.items()} == expected
    assert {name for name, e in entries.items() if e.needs} == {"instant-ngp/fox"}
    assert entries["instant-ngp/fox"].needs == (("missing_images", "skip"),)
    for entry in entries.values():  # each digest says where it came from: a source, or that it is recorded
        assert ("nerfbaselines pins it (nerfbaselines/datasets/" in entry.sha256_from) == (entry.sha256 is not None)


def test_each_format_is_a_data_group_that_reads_a_folder_and_builds_its_reader():
    assert folder_formats() == {"blender": "nerfexp.data.blender.BlenderScene",
                                "colmap": "nerfexp.data.colmap.ColmapScene", "llff": "nerfexp.data.llff.LLFFScene",
                                "nerfstudio": "nerfexp.data.nerfstudio.NerfstudioScene"}


def catalogue(tmp_path, text: str):
    path = tmp_path / "lab.yaml"
    path.write_text(text)
    return path


def entry_text(**changes) -> str:
    """One entry as YAML: ``ENTRY`` with ``changes`` (None removes a key)."""
    entry = {**ENTRY, **changes}
    return yaml.safe_dump([{key: value for key, value in entry.items() if value is not None}], sort_keys=False)


def test_a_users_entry_in_the_issues_form_is_read_with_every_optional_key(tmp_path):
    path = catalogue(tmp_path, entry_text(url=["https://a/chair.zip", "http://b:8080/x/chair.zip"], size=1234,
                                          needs={"downscale": 2}, note="the lab's chair", sha256_from="our server"))
    (entry,) = read_catalog(path)
    assert (entry.name, entry.format, entry.urls, entry.sha256, entry.size, entry.path, entry.needs, entry.note,
            entry.sha256_from, entry.catalog) == (
        "mylab/chair", "blender", ("https://a/chair.zip", "http://b:8080/x/chair.zip"), "ab" * 32, 1234, "chair",
        (("downscale", 2),), "the lab's chair", "our server", str(path))
    (recorded,) = read_catalog(catalogue(tmp_path, entry_text().replace('ab' * 32, 'null')))
    assert recorded.sha256 is None and recorded.sha256_from == "none published: recorded on first download"


MISTAKES = {  # changes to the entry -> the line's end (after "FILE: entry 0 (mylab/chair): ")
    "no sha256": ({"sha256": None}, "missing key 'sha256' (an entry has name, format, url, sha256, path; may have "
                                    "size, sha256_from, needs, note)"),
    "a short digest": ({"sha256": "ab" * 31}, f"'sha256': expected 64 lowercase hexadecimal digits (the archive's "
                                              f"SHA-256), or null (none published: recorded on first download), got "
                                              f"'{'ab' * 31}'"),
    "an upper-case digest": ({"sha256": "AB" * 32}, "'sha256': expected 64 lowercase hexadecimal digits"),
    "a local file": ({"url": "file:///etc/passwd"}, "'url': expected an http(s) address, or a non-empty list of them, "
                                                    "got 'file:///etc/passwd'"),
    "ftp": ({"url": "ftp://host/chair.zip"}, "'url': expected an http(s) address"),
    "no host": ({"url": "https:///chair.zip"}, "'url': expected an http(s) address"),
    "an empty list": ({"url": []}, "'url': expected an http(s) address, or a non-empty list of them, got []"),
    "a climbing path": ({"path": "../chair"}, "'path': expected the scene's folder inside the archive: a relative "
                                              "path without '..', got '../chair'"),
    "an absolute path": ({"path": "/chair"}, "'path': expected the scene's folder inside the archive"),
    "another format": ({"format": "procedural"}, "'format': expected one of blender, colmap, llff, nerfstudio (a data "
                                                 "group that reads a folder), got 'procedural'"),
    "a size of text": ({"size": "1 GB"}, "'size': expected the archive's bytes, a whole number in [1, 2^44], or null "
                                         "(not known), got '1 GB'"),
    "a typo": ({"sha265": "x"}, "unknown key 'sha265' (an entry has name, format, url, sha256, path; may have size, "
                                "sha256_from, needs, note; the closest: sha256)"),
    "needs of a list": ({"needs": ["skip"]}, "'needs': expected a mapping of data settings to values"),
}


@pytest.mark.parametrize("changes, line", MISTAKES.values(), ids=MISTAKES)
def test_each_malformed_key_of_an_entry_is_one_line_naming_the_file_the_entry_and_the_key(tmp_path, changes, line):
    path = catalogue(tmp_path, entry_text(**changes))
    with pytest.raises(ConfigError) as refused:
        read_catalog(path)
    assert str(refused.value).startswith(f"{path}: entry 0 (mylab/chair): {line}")


@pytest.mark.parametrize("text, line", [
    ("", "expected a YAML list of scene entries (- name: ..., format: ..., url: ..., sha256: ..., path: ...), "
         "got None"),
    ("name: mylab/chair\n", "expected a YAML list of scene entries"),
    ("- just a name\n", "entry 0: expected a mapping with the keys name, format, url, sha256, path, got 'just a name'"),
    (entry_text() + entry_text(path="chair2"), "entry 1: the name 'mylab/chair' is given twice"),
    (entry_text(name="MyLab/Chair"), "entry 0 (MyLab/Chair): 'name': expected a scene's name: lowercase words"),
    ("- &a [1]\n- *a\n", "line 1: a YAML anchor or alias, which nerfexp does not read"),
], ids=["empty", "a mapping", "a text", "a name twice", "capitals", "an alias"])
def test_a_catalogue_that_is_not_a_list_of_entries_is_one_line_naming_it(tmp_path, text, line):
    path = catalogue(tmp_path, text)
    with pytest.raises(ConfigError) as refused:
        read_catalog(path)
    assert str(refused.value).startswith(f"{path}: {line}")


def test_a_users_entry_may_not_take_one_of_nerfexps_names_and_a_missing_file_is_named(tmp_path):
    path = catalogue(tmp_path, entry_text(name="blender/lego"))
    with pytest.raises(ConfigError, match=r"lab.yaml: the name 'blender/lego' is one of nerfexp's own scenes "
                                          r"\(nerfexp-data list\): choose another$"):
        catalog_entries(path)
    with pytest.raises(ConfigError) as refused:
        catalog_entries(tmp_path / "missing.yaml")
    assert str(refused.value) == f"data.catalog={tmp_path / 'missing.yaml'}: cannot be read (No such file or directory)"


def test_a_users_scenes_are_found_beside_nerfexps_and_an_unknown_name_names_the_closest(tmp_path):
    path = catalogue(tmp_path, entry_text())
    assert find_entry("mylab/chair", path).path == "chair" and find_entry("blender/lego", path).format == "blender"
    with pytest.raises(ConfigError) as refused:
        find_entry("mylab/chiar", path)
    assert str(refused.value) == (f"scene mylab/chiar: expected a scene nerfexp's catalogue or {path} names (the "
                                  "closest: mylab/chair, blender/chair; nerfexp-data list names them all)")
    with pytest.raises(ConfigError, match="the closest: blender/lego, "):
        find_entry("blender/legoo", None)


def config(scene: str, target: str = "nerfexp.data.blender.BlenderScene", **more) -> dict:
    """A scene's resolved config as the settings check sees it: the arguments and ``_target_``."""
    return {"_target_": target, "root": None, "scene": scene, "catalog": None, **more}


def test_a_scene_by_name_is_checked_against_the_chosen_data_group_and_what_it_needs():
    assert scene_problem(config("blender/lego")) is None
    assert scene_problem({**config("blender/lego"), "root": "/data/lego"}) is None  # a folder given: no name read
    assert scene_problem(config("llff/fern")) == (
        "data=llff with it: the catalogue reads llff/fern with data=llff (nerfexp.data.llff.LLFFScene), and this data "
        "builds nerfexp.data.blender.BlenderScene")
    fox = format_target("nerfstudio")
    assert scene_problem(config("instant-ngp/fox", fox, missing_images="skip")) is None
    assert scene_problem(config("instant-ngp/fox", fox, missing_images="refuse")).startswith(
        "data.missing_images=skip with it: instant-ngp/fox needs it (its transforms.json lists 67 frames and the "
        "repository keeps the images of 50;")
    assert scene_problem(config("blender/lgo")).startswith(
        "a scene nerfexp's catalogue names (the closest: blender/lego")


def test_a_mirror_replaces_each_addresss_scheme_and_host_and_keeps_its_path_and_query():
    cases = [
        ("https://storage.googleapis.com/gresearch/refraw360/360_v2.zip", "http://127.0.0.1:8123",
         "http://127.0.0.1:8123/gresearch/refraw360/360_v2.zip"),
        (GDRIVE.format("ID"), "https://mirror.lab/nerf/", "https://mirror.lab/nerf/download?id=ID&export=download"
                                                          "&confirm=t"),
        ("https://github.com/NVlabs/instant-ngp/archive/abc.zip", None,
         "https://github.com/NVlabs/instant-ngp/archive/abc.zip"),
    ]
    for url, mirror, expected in cases:
        assert mirrored(url, mirror) == expected
    for mirror in ("ftp://host", "file:///data", "http://", "http://host/?q=1", "http://host/#x", "host:8000",
                   "http://host:port", "http://a b"):
        assert not MIRROR[1](mirror), mirror
    assert MIRROR[1]("https://mirror.lab/nerf") and is_web_address("http://127.0.0.1:1/x?id=2")
