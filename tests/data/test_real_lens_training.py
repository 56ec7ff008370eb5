"""Ground truth for real cameras: the built-in scene rendered through a lens with its principal point off the
centre, fx != fy and OPENCV distortion, written in nerfstudio's format, trains as well as the same scene
rendered through an ideal pinhole, and measurably better than when its intrinsics are ignored (a centred
pinhole of focal length fx, the reader nerfexp had before ``data=nerfstudio``)."""

import json

import pytest
import torch

from nerfexp.data.procedural import load_procedural
from nerfexp.data.transforms_file import TRANSFORMS, write_nerfstudio
from nerfexp.geometry.lenses import Intrinsics, distortion_vector
from tests.helpers import run_nerfexp

SIZE = 32
MARGIN_DB = 1.0  # the real lens read with its intrinsics: within this of the pinhole scene's test PSNR
WORSE_DB = 1.0  # ignoring the intrinsics: at least this much below


def strong_lens() -> Intrinsics:
    """A lens whose intrinsics matter at 32 x 32 pixels: the principal point 3 and 2 pixels off the centre,
    fx and fy 8% apart, barrel distortion that moves the corners by about 2 pixels."""
    params = torch.tensor([46.0, 42.5, 19.0, 14.0], dtype=torch.float64)
    return Intrinsics(params, distortion_vector({"k1": -0.2, "k2": 0.05, "p1": 0.003, "p2": -0.004}),
                      torch.tensor(False))


def write_scene(root, lens: Intrinsics | None) -> None:
    splits = (("train", 30), ("val", 1), ("test", 4))
    write_nerfstudio(root, ((split, load_procedural(split, n, SIZE, SIZE, supersample=1, lens=lens))
                            for split, n in splits))


@pytest.mark.slow
def test_a_real_lens_trains_as_well_as_a_pinhole_and_ignoring_it_costs(tmp_path):
    write_scene(tmp_path / "real", strong_lens())
    write_scene(tmp_path / "pinhole", None)
    content = json.loads((tmp_path / "real" / TRANSFORMS).read_text())
    ignored = {key: value for key, value in content.items() if key not in ("k1", "k2", "k3", "p1", "p2")}
    ignored.update(camera_model="PINHOLE", fl_y=content["fl_x"], cx=SIZE / 2, cy=SIZE / 2)
    (tmp_path / "real" / "ignored.json").write_text(json.dumps(ignored))
    scores = {}
    for name, root, transforms in (("real", "real", TRANSFORMS), ("ignored", "real", "ignored.json"),
                                   ("pinhole", "pinhole", TRANSFORMS)):
        run_dir = tmp_path / f"run_{name}"
        result = run_nerfexp("data=nerfstudio", f"data.root={tmp_path / root}", f"data.transforms={transforms}",
                             "data.near=2", "data.far=6", "encoding=hashgrid", "scale=cpu", "scale.steps=150",
                             "scale.val_every=150", "scale.n_coarse=16", "scale.n_fine=32", "model.lpips=false",
                             "trainer.enable_progress_bar=false", f"hydra.run.dir={run_dir}", cwd=tmp_path)
        assert result.returncode == 0, result.stderr[-3000:]
        scores[name] = json.loads((run_dir / "results.json").read_text())["test_psnr"]
    assert scores["real"] > scores["pinhole"] - MARGIN_DB, scores
    assert scores["ignored"] < scores["real"] - WORSE_DB, scores
