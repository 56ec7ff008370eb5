"""``nerfexp-scene``: the built-in scene written as a Blender-format dataset that loads back as rendered."""

import torch

from nerfexp import scene
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
