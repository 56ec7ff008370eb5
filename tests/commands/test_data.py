"""Scenes by name from the command line: ``nerfexp data=blender data.scene=NAME`` trains from a catalogue entry served
by a server on 127.0.0.1 (the entry's host replaced by ``data.mirror``) and a run read back finds it offline; each
failure of the fetch, and each setting that cannot name a scene, is one line with the cache as it was;
``nerfexp-data`` lists the scenes and fetches one. nerfexp's own entries are reached through the mirror only: no test
contacts their hosts."""

import hashlib
import json
import math

import pytest
import yaml

from nerfexp.data.nerfstudio import NerfstudioScene
from nerfexp.data.procedural import load_procedural
from nerfexp.data.scene_cache import CACHE_VARIABLE, scene_folder
from nerfexp.data.transforms_file import write_nerfstudio
from nerfexp.downloads import ATTEMPTS
from tests.data.archive_files import Item, folder_files, folder_items, scene_items, zip_bytes
from tests.data.archive_server import Served, local_only, no_network, serving
from tests.helpers import digests, fill_disk, one_error_line, read_json, run_nerfexp, small_disk

PATH = "/lab/chair.zip"
ARCHIVE = zip_bytes(scene_items("chair"))
FOX_COMMIT = "abe236ee00cf90cfca6e36e65c00435d5b21f50a"


@pytest.fixture(autouse=True)
def local(monkeypatch) -> list:
    """No connection but to 127.0.0.1 (the servers these tests start)."""
    return local_only(monkeypatch)


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """The scene cache of the commands these tests run (``NERFEXP_DATA``), empty."""
    folder = tmp_path / "cache"
    monkeypatch.setenv(CACHE_VARIABLE, str(folder))
    return folder


def lab_catalogue(folder, **changes) -> str:
    """A user's catalogue of one scene, in the issue's form (``changes`` to its entry), written into ``folder``."""
    entry = {"name": "mylab/chair", "format": "blender", "url": f"https://scenes.mylab.example{PATH}",
             "sha256": hashlib.sha256(ARCHIVE).hexdigest(), "path": "chair", **changes}
    path = folder / "lab.yaml"
    path.write_text(yaml.safe_dump([entry], sort_keys=False))
    return str(path)


def blender_overrides(tiny) -> list[str]:
    """The tiny run's overrides for a Blender-format scene (``tests.test_bad_input.blender_scene``'s)."""
    return [o for o in tiny if not o.startswith(("data.", "scale.image_size"))] + ["data.n_val=1"]


@pytest.mark.slow
def test_a_scene_by_name_trains_records_its_digest_and_is_read_back_offline(tmp_path, cache, tiny, monkeypatch):
    catalogue = lab_catalogue(tmp_path)
    with serving({PATH: Served(ARCHIVE)}) as server:
        result = run_nerfexp("data=blender", "data.scene=mylab/chair", f"data.catalog={catalogue}",
                             f"data.mirror={server.address}", *blender_overrides(tiny),
                             f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert server.requests == [(PATH, None)]
    results = read_json(tmp_path / "run" / "results.json")
    digest = hashlib.sha256(ARCHIVE).hexdigest()
    assert {key: results["scene"][key] for key in ("name", "sha256", "checksum", "url", "catalog", "folder")} == {
        "name": "mylab/chair", "sha256": digest, "checksum": "pinned", "url": f"https://scenes.mylab.example{PATH}",
        "catalog": catalogue, "folder": str(scene_folder(cache, "mylab/chair"))}
    assert results["config"]["data"]["scene"] == "mylab/chair" and math.isfinite(results["test_psnr"])
    assert (cache / "archives" / digest).read_bytes() == ARCHIVE
    tried = no_network(monkeypatch)  # offline: the run read back finds its scene in the cache (no LPIPS download)
    evaluated = run_nerfexp(str(tmp_path / "run"), "model.lpips=false", cwd=tmp_path, script="nerfexp-eval")
    assert evaluated.returncode == 0, evaluated.stderr[-3000:]
    assert read_json(tmp_path / "run" / "eval.json")["test_psnr"] == pytest.approx(results["test_psnr"], abs=1e-4)
    assert tried == []


def pinned(data: bytes) -> tuple[dict, Served]:
    """An archive served as it is, its digest pinned by the entry: what fails lies in its members."""
    return {"sha256": hashlib.sha256(data).hexdigest()}, Served(data)


FETCH_FAILURES = {  # the entry's changes, what is served, the line's words
    "a changed byte": ({}, Served(ARCHIVE[:-40] + bytes([ARCHIVE[-40] ^ 1]) + ARCHIVE[-39:]),
                       f"checksum mismatch: its SHA-256 is {{found}}, expected {hashlib.sha256(ARCHIVE).hexdigest()}"),
    "a wrong size": ({"size": len(ARCHIVE) - 1}, Served(ARCHIVE),
                     f"size mismatch: the server's file is {len(ARCHIVE):,} bytes, expected {len(ARCHIVE) - 1:,}"),
    "a member that escapes": (*pinned(zip_bytes([*scene_items("chair"), Item("chair/../../../.bashrc", data=b"x")])),
                              "member 'chair/../../../.bashrc' would be written outside the folder"),
    "an interrupted download": ({}, Served(ARCHIVE, cut_at=1000, cuts=100),
                                f"the transfer broke off {ATTEMPTS} times in a row at byte 1,000"),
}


@pytest.mark.parametrize("changes, served, words", FETCH_FAILURES.values(), ids=FETCH_FAILURES)
def test_a_fetch_that_fails_is_one_line_of_the_command_and_leaves_the_cache_as_it_was(tmp_path, cache, tiny, changes,
                                                                                      served, words):
    with serving({"/lab/table.zip": Served(zip_bytes(scene_items("table", seed=2))), PATH: served}) as server:
        table = lab_catalogue(tmp_path, name="mylab/table", path="table", url="https://x.example/lab/table.zip",
                              sha256=hashlib.sha256(zip_bytes(scene_items("table", seed=2))).hexdigest())
        fetched = run_nerfexp("fetch", "mylab/table", "--catalog", table, "--mirror", server.address, cwd=tmp_path,
                              script="nerfexp-data")
        assert fetched.returncode == 0, fetched.stderr[-2000:]
        before = digests(cache)
        catalogue = lab_catalogue(tmp_path, **changes)
        result = run_nerfexp("data=blender", "data.scene=mylab/chair", f"data.catalog={catalogue}",
                             f"data.mirror={server.address}", *blender_overrides(tiny),
                             f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    line = one_error_line(result)
    assert line.startswith("nerfexp: error: scene mylab/chair: ") and words.format(
        found=hashlib.sha256(served.data).hexdigest()) in line, line
    assert digests(cache) == before
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_a_full_disk_while_fetching_is_one_line_and_leaves_the_cache_as_it_was(tmp_path, tiny, monkeypatch):
    with small_disk(tmp_path / "disk", "1m") as disk:
        monkeypatch.setenv(CACHE_VARIABLE, str(disk / "cache"))
        (disk / "cache").mkdir()
        fill_disk(disk / "filler", len(ARCHIVE) // 3)
        with serving({PATH: Served(ARCHIVE)}) as server:
            result = run_nerfexp("data=blender", "data.scene=mylab/chair", f"data.catalog={lab_catalogue(tmp_path)}",
                                 f"data.mirror={server.address}", *blender_overrides(tiny),
                                 f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
        assert one_error_line(result) == (f"nerfexp: error: scene mylab/chair: no space left on the disk of "
                                          f"{disk / 'cache'} (No space left on device): the cache is as it was")
        assert digests(disk / "cache") == {}


SETTINGS = {  # overrides -> the line (after "nerfexp: error: ")
    "neither": (["data=blender"], "data.root=None, data.scene=None: expected a scene's folder, data.root=DIR, or a "
                                  "scene's name, data.scene=NAME (nerfexp-data list names them; docs/data.md)"),
    "an unknown name": (["data=blender", "data.scene=blender/legoo"],
                        "data.scene=blender/legoo: expected a scene nerfexp's catalogue names (the closest: "
                        "blender/lego, blender/hotdog, blender/mic; nerfexp-data list names them all)"),
    "another format": (["data=llff", "data.scene=blender/lego"],
                       "data.scene=blender/lego: expected data=blender with it: the catalogue reads blender/lego with "
                       "data=blender (nerfexp.data.blender.BlenderScene), and this data builds "
                       "nerfexp.data.llff.LLFFScene"),
    "what the fox needs": (["data=nerfstudio", "data.scene=instant-ngp/fox"],
                           "data.scene=instant-ngp/fox: expected data.missing_images=skip with it: instant-ngp/fox "
                           "needs it (its transforms.json lists 67 frames and the repository keeps the images of 50; "
                           "data.missing_images=skip leaves the other 17 out, as Instant-NGP's loader does)"),
    "a folder and a name": (["data=blender", "data.root=/data/lego", "data.scene=blender/lego"],
                            "data.scene=blender/lego: not used with data.root=/data/lego (the folder given is read; "
                            "data.scene names none then)"),
    "a mirror without a name": (["data=blender", "data.root=/data/lego", "data.mirror=http://127.0.0.1:1"],
                                "data.mirror=http://127.0.0.1:1: not used with data.root=/data/lego (the folder given "
                                "is read; data.scene names none then)"),
    "a mirror that is no address": (["data=blender", "data.scene=blender/lego", "data.mirror=file:///srv"],
                                    "data.mirror=file:///srv: expected an http(s)://HOST[:PORT][/PATH] address without "
                                    "a query, or null (each source's own host)"),
    "a catalogue not there": (["data=blender", "data.scene=mylab/chair", "data.catalog=/no/lab.yaml"],
                              "data.catalog=/no/lab.yaml: cannot be read (No such file or directory)"),
}


@pytest.mark.parametrize("overrides, line", SETTINGS.values(), ids=SETTINGS)
def test_a_setting_that_names_no_scene_it_can_read_is_one_line_before_the_run_directory_is_made(
        tmp_path, cache, overrides, line):
    result = run_nerfexp(*overrides, f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert one_error_line(result) == f"nerfexp: error: {line}"
    assert not (tmp_path / "run").exists() and not cache.exists()  # nothing made, nothing downloaded


def test_a_malformed_catalogue_is_one_line_naming_its_file_entry_and_key(tmp_path, cache):
    catalogue = lab_catalogue(tmp_path, sha256="0" * 63)
    result = run_nerfexp("data=blender", "data.scene=mylab/chair", f"data.catalog={catalogue}",
                         f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert one_error_line(result).startswith(f"nerfexp: error: {catalogue}: entry 0 (mylab/chair): 'sha256': expected "
                                             "64 lowercase hexadecimal digits")
    assert not (tmp_path / "run").exists()


def test_nerfexp_data_lists_every_scene_and_fetches_one_which_is_then_found_offline(tmp_path, cache, monkeypatch):
    catalogue = lab_catalogue(tmp_path)
    listed = run_nerfexp("list", "--catalog", catalogue, cwd=tmp_path, script="nerfexp-data")
    assert listed.returncode == 0, listed.stderr
    lines = listed.stdout.splitlines()
    assert lines[0] == f"scenes by name (data.scene=NAME); the cache: {cache}"
    rows = {line.split()[0]: line.split() for line in lines[2:]}
    assert len(rows) == 27 and rows["blender/lego"][1:3] == ["data=blender", "no"]
    assert rows["blender/lego"][3:5] == ["pinned", "f01fd1b4ab045b0d453917346f26f898657bb5bec4834b95fdad1f361826e45e"]
    assert rows["mipnerf360/garden"][1:] == ["data=colmap", "no", "recorded", "on", "first", "download", "(none",
                                             "yet)", "storage.googleapis.com"]
    assert rows["instant-ngp/fox"][1:3] == ["data=nerfstudio", "data.missing_images=skip"]
    assert rows["mylab/chair"][1:3] == ["data=blender", "no"]
    with serving({PATH: Served(ARCHIVE)}) as server:
        fetched = run_nerfexp("fetch", "mylab/chair", "--catalog", catalogue, "--mirror", server.address,
                              cwd=tmp_path, script="nerfexp-data")
    assert fetched.returncode == 0, fetched.stderr
    assert fetched.stdout.strip() == (f"mylab/chair: {scene_folder(cache, 'mylab/chair')} (data=blender; its archive's "
                                      f"SHA-256 {hashlib.sha256(ARCHIVE).hexdigest()}, pinned)")
    assert f"nerfexp-data: scene mylab/chair: downloading {server.url(PATH)} into {cache}" in fetched.stderr
    tried = no_network(monkeypatch)
    again = run_nerfexp("fetch", "mylab/chair", "--catalog", catalogue, cwd=tmp_path, script="nerfexp-data")
    assert again.stdout == fetched.stdout and tried == []
    relisted = run_nerfexp("list", "--catalog", catalogue, cwd=tmp_path, script="nerfexp-data")
    assert [line.split()[2] for line in relisted.stdout.splitlines() if line.startswith("mylab/chair ")] == ["yes"]
    assert one_error_line(run_nerfexp("fetch", "mylab/chiar", "--catalog", catalogue, cwd=tmp_path,
                                      script="nerfexp-data"), "nerfexp-data").startswith(
        f"nerfexp-data: error: scene mylab/chiar: expected a scene nerfexp's catalogue or {catalogue} names (the "
        "closest: mylab/chair")


def test_nerfexps_own_entries_are_fetched_through_the_mirror_and_checked_against_their_pinned_digest(tmp_path, cache):
    drive = "/download?id=18JxhpWD-4ZmuFKLzKlAw-w5PpzZxXOcG&export=download&confirm=t"
    with serving({drive: Served(zip_bytes(scene_items("nerf_synthetic/lego")))}) as server:
        result = run_nerfexp("fetch", "blender/lego", "--mirror", server.address, cwd=tmp_path, script="nerfexp-data")
    assert server.requests == [(drive, None)]  # the host the entry names, replaced: Google Drive never reached
    line = one_error_line(result, "nerfexp-data")
    assert ("expected f01fd1b4ab045b0d453917346f26f898657bb5bec4834b95fdad1f361826e45e (pinned: nerfbaselines pins it "
            "(nerfbaselines/datasets/blender.py)): nothing of it kept in") in line  # tests' bytes are not the scene's
    assert digests(cache) == {}


def fox_archive(tmp_path) -> bytes:
    """Instant-NGP's repository as GitHub's archive holds it, shrunk: the fox a tiny nerfstudio scene of 9 frames
    whose file lists 3 more frames without images (as its 67 frames for 50 images)."""
    scene = tmp_path / "fox"
    write_nerfstudio(scene, ((split, load_procedural(split, n, 24, 24, supersample=1))
                             for split, n in (("train", 8), ("val", 1), ("test", 3))))
    content = json.loads((scene / "transforms.json").read_text())
    for key in ("train_filenames", "val_filenames", "test_filenames"):
        del content[key]
    (scene / "transforms.json").write_text(json.dumps(content))
    for name in ("train_0001.png", "train_0004.png", "test_0002.png"):
        (scene / "images" / name).unlink()
    return zip_bytes([Item(f"instant-ngp-{FOX_COMMIT}/README.md", data=b"Instant-NGP"),
                      *folder_items(scene, f"instant-ngp-{FOX_COMMIT}/data/nerf/fox")])


def test_the_fox_as_served_is_fetched_its_digest_recorded_and_read_without_its_missing_images(tmp_path, cache):
    path = f"/NVlabs/instant-ngp/archive/{FOX_COMMIT}.zip"
    archive = fox_archive(tmp_path)
    with serving({path: Served(archive)}) as server:
        result = run_nerfexp("fetch", "instant-ngp/fox", "--mirror", server.address, cwd=tmp_path,
                             script="nerfexp-data")
    assert result.returncode == 0, result.stderr
    assert f"its archive's SHA-256 {hashlib.sha256(archive).hexdigest()}, recorded on first download" in result.stdout
    assert "no SHA-256 is published for https://github.com/NVlabs/instant-ngp/archive/" in result.stderr
    scene = NerfstudioScene(scene="instant-ngp/fox", missing_images="skip")  # the cache's folder, by name, offline
    assert scene.folder() == scene_folder(cache, "instant-ngp/fox")
    assert sum(len(scene.views(split)) for split in ("train", "test")) == 9
    assert scene.frames_left_out() == ["images/test_0002.png", "images/train_0001.png", "images/train_0004.png"]
    assert scene.source()["checksum"] == "recorded on first download"
    assert set(folder_files(scene.folder())) >= {"transforms.json", "images/train_0000.png"}
