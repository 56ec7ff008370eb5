"""``nerfexp-scene``: the built-in scene written as a Blender-format dataset that loads back as rendered."""

import json
import shutil

import pytest
import torch

from nerfexp.commands import scene
from nerfexp.data.blender import load_blender
from nerfexp.data.procedural import load_procedural


def test_nerfexp_scene_writes_three_splits(tmp_path):
    scene.main([str(tmp_path), "--resolution", "16", "--n-train", "3", "--n-val", "1", "--n-test", "2",
                "--supersample", "1"])
    assert sorted(p.name for p in tmp_path.glob("transforms_*.json")) == [
        "transforms_test.json", "transforms_train.json", "transforms_val.json"]
    for split, n in (("train", 3), ("val", 1), ("test", 2)):
        assert len(list((tmp_path / split).glob("*.png"))) == n
    loaded, rendered = load_blender(tmp_path, "test"), load_procedural("test", 2, 16, 16, supersample=1)
    torch.testing.assert_close(loaded.rgba, rendered.rgba, atol=0.5 / 255, rtol=0)
    torch.testing.assert_close(loaded.c2w, rendered.c2w)


def scene_files(folder) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def write_tiny(folder, n_train: int = 2) -> None:
    scene.main([str(folder), "--resolution", "8", "--n-train", str(n_train), "--n-val", "1", "--n-test", "1",
                "--supersample", "1"])


def test_nerfexp_scene_replaces_its_own_scene_and_refuses_any_other_folder(tmp_path, tiny_run):
    own = tmp_path / "scene"
    write_tiny(own, n_train=3)
    write_tiny(own, n_train=2)  # its own folder: replaced as a whole, no view of the first left
    assert sorted(p.name for p in (own / "train").iterdir()) == ["r_0.png", "r_1.png"]
    assert json.loads((own / scene.MARKER).read_text())["views"] == {"train": 2, "val": 1, "test": 1}

    dataset = tmp_path / "dataset"  # a dataset (no marker); a run directory (another command's manifest)
    shutil.copytree(own, dataset, ignore=shutil.ignore_patterns(scene.MARKER))
    run_dir = shutil.copytree(tiny_run, tmp_path / "run", ignore=shutil.ignore_patterns("render", "export"))
    for folder, shown in ((dataset, "test/r_0.png, train/r_0.png, train/r_1.png, ..."),
                          (run_dir, ".hydra/config.yaml, .hydra/hydra.yaml, .hydra/overrides.yaml, ...")):
        before = scene_files(folder)
        with pytest.raises(SystemExit) as exit:
            write_tiny(folder)
        assert exit.value.code == (f"nerfexp-scene: error: {folder} holds files nerfexp-scene did not make "
                                   f"({shown}): choose a new or empty folder")
        assert scene_files(folder) == before

    (own / "notes.txt").write_text("mine")  # its own scene with a user's file, and a view changed since
    (own / "train" / "r_0.png").write_bytes(b"a user's own photograph")
    before = scene_files(own)
    with pytest.raises(SystemExit) as exit:
        write_tiny(own)
    assert exit.value.code == (f"nerfexp-scene: error: {own / 'notes.txt'}, {own / 'train/r_0.png'} are not files "
                               f"nerfexp-scene wrote (they are not in {own / 'nerfexp-manifest.json'}, or changed "
                               "since): move them elsewhere, or choose a new or empty folder")
    assert scene_files(own) == before


@pytest.mark.parametrize(("arguments", "refused"), [
    (["--resolution", "9" * 40], f"--resolution {'9' * 40} --n-train 100 --supersample 2: a split of 100 views needs "
                                 "about 2^279 bytes of memory"),
    (["--n-val", "9" * 400], f"--resolution 100 --n-val {'9' * 400} --supersample 2: a split of {'9' * 400} views "
                             "needs about 2^1349 bytes of memory"),  # past any float: said as a power of two
])
def test_a_count_too_large_to_render_is_one_line_whatever_its_size(tmp_path, arguments, refused):
    # issue 39 section 4: every number a command takes has a range; these counts are bounded by memory
    with pytest.raises(SystemExit) as exit:
        scene.main([str(tmp_path / "scene"), *arguments])
    assert str(exit.value.code).startswith(f"nerfexp-scene: error: {refused}")
    assert not (tmp_path / "scene").exists()
