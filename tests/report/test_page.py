"""``report.html``: the page rendered by a real headless browser shows each variant's render, the ground
truth and the error heat maps (images of known colours found in the screenshot, not broken-image boxes);
labels from runs are text, not markup; the page fetches nothing; the views shown and bad ``--views``."""

import json
import re
from pathlib import Path

import numpy as np
import pytest
from matplotlib import colormaps
from PIL import Image

from nerfexp.commands.report import main
from nerfexp.report.folder import write_report
from nerfexp.report.pictures import ERROR_WHITE, default_views
from nerfexp.scoring.perceptual import ALEXNET_SHA256
from tests.browser import screenshot
from tests.helpers import make_run

SIZE = 16  # pixels of the runs' test images; the page enlarges them
TRUTH, RED, BLUE = (0, 200, 0), (220, 0, 0), (0, 0, 220)
N_VIEWS = 8


def write_png(path: Path, colour, size: int = SIZE) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.full((size, size, 3), colour, np.uint8)).save(path)


def add_test_views(run: Path, render, error, psnr: list[float]) -> None:
    """Test renders of one colour, error images of one value, and per-view scores with their means as the headline
    scores, as a run leaves them."""
    for i in range(N_VIEWS):
        write_png(run / "test" / f"r_{i}.png", render)
        write_png(run / "test" / f"r_{i}_target.png", TRUTH)
        write_png(run / "test" / f"r_{i}_error.png", error)
    results = json.loads((run / "results.json").read_text())
    results.update(test_psnr=float(np.mean(psnr)), test_ssim=0.5, test_views=list(range(N_VIEWS)),
                   test_psnr_per_view=psnr, test_ssim_per_view=[0.5] * N_VIEWS, config={"seed": int(run.name)})
    (run / "results.json").write_text(json.dumps(results))


@pytest.fixture
def pictured(tmp_path) -> Path:
    """Variant red: seeds 0 and 1 (seed 1 renders blue, so a page showing it instead of seed 0 fails), no
    error; variant blue: seed 0, error 0.25 everywhere (white on the heat map)."""
    root = tmp_path / "sweep"
    per_view = [20.0 + i for i in range(N_VIEWS)]
    add_test_views(make_run(root, "0", ["model=red", "seed=0"]), RED, (0, 0, 0), per_view)
    add_test_views(make_run(root, "1", ["model=red", "seed=1"]), BLUE, (0, 0, 0), per_view)
    white = round(ERROR_WHITE * 255)
    add_test_views(make_run(root, "2", ["model=blue", "seed=0"]), BLUE, (white,) * 3, per_view[::-1])
    return root


def covered(shot: np.ndarray, colour, tolerance: int = 3) -> int:
    """Pixels of the screenshot [H, W, 3] within ``tolerance`` of ``colour`` in every channel."""
    return int((np.abs(shot.astype(int) - np.array(colour)) <= tolerance).all(-1).sum())


def test_the_page_in_a_real_browser_shows_every_picture_at_its_size(pictured, tmp_path):
    write_report([pictured], pictured, views=[0, 7])
    shot = screenshot((pictured / "report.html").as_uri(), tmp_path / "page.png", 1400, 3000)
    picture = 192 * 192  # each picture's CSS size, at a device scale of 1
    black, white = (colormaps["magma"](np.array([0.0, 1.0]), bytes=True)[:, :3]).tolist()
    # per view (2): the truth once, red once (variant red's seed 0), blue once (variant blue), the red
    # variant's error black and the blue variant's white on the heat map; nothing else has these colours
    for colour, count in [(TRUTH, 2), (RED, 2), (BLUE, 2), (black, 2), (white, 2)]:
        assert abs(covered(shot, colour) / picture - count) < 0.05, (colour, covered(shot, colour) / picture)
    html = (pictured / "report.html").read_text()
    assert "PSNR 20.00 dB, SSIM 0.500, seed 0" in html and "PSNR 27.00 dB" in html  # view 0 of each variant
    assert "PSNR 27.00 dB, SSIM 0.500, seed 0" in html and "PSNR 20.00 dB" in html  # view 7, reversed


def test_a_view_is_captioned_with_its_lpips_where_the_run_scored_it(pictured):
    results_file = pictured / "0" / "results.json"
    results = json.loads(results_file.read_text())
    per_view = [0.125 + i / 100 for i in range(N_VIEWS)]
    results.update(test_lpips=float(np.mean(per_view)), test_lpips_per_view=per_view,
                   lpips_weights_sha256=ALEXNET_SHA256)  # as a run scored with the published weights records
    results_file.write_text(json.dumps(results))
    write_report([pictured], pictured, views=[0, 7])
    html = (pictured / "report.html").read_text()
    assert "PSNR 20.00 dB, SSIM 0.500, LPIPS 0.125, seed 0" in html and "LPIPS 0.195, seed 0" in html
    assert "PSNR 27.00 dB, SSIM 0.500, seed 2" in html  # the other variant's run did not score LPIPS


def test_the_page_fetches_nothing_and_shows_labels_as_text(tmp_path):
    root = tmp_path / "sweep"
    add_test_views(make_run(root, "0", ["note=<script>alert(1)</script>", "seed=0"]), RED, (0, 0, 0), [20.0] * 8)
    add_test_views(make_run(root, "1", ["note=[x](javascript:alert(2))", "seed=0"]), RED, (0, 0, 0), [20.0] * 8)
    write_report([root], root)
    html = (root / "report.html").read_text()
    assert "<script" not in html and "&lt;script&gt;" in html
    assert 'href="javascript' not in html
    assert "Content-Security-Policy" in html and "default-src 'none'" in html
    sources = re.findall(r'(?:src|href)="([^"]*)"', html)
    assert sources and all(not re.match(r"[a-z]+:", s) for s in sources)  # relative: no http:, no file:
    assert all((root / s).is_file() for s in sources)  # every one in the report's folder


def test_default_views_spread_from_the_first_to_the_last():
    assert default_views(8) == [0, 4, 7]
    assert default_views(2) == [0, 1] and default_views(1) == [0] and default_views(0) == []
    assert default_views(5, count=5) == [0, 1, 2, 3, 4]


def test_views_not_in_the_runs_are_one_line_and_a_damaged_render_is_named(pictured, tmp_path):
    with pytest.raises(SystemExit, match=r"--views 9 12: not a test view of the runs shown \(they have views 0 to 7\)"):
        main([str(pictured), "--views", "9", "3", "12", "--out", str(tmp_path / "out")])
    assert not (tmp_path / "out").exists()  # refused before anything is written
    (pictured / "2" / "test" / "r_4.png").write_bytes(b"\x89PNG\r\n\x1a\n not an image")
    (pictured / "2" / "test" / "r_4_error.png").unlink()
    write_report([pictured], pictured)  # default views: 0, 4, 7
    html = (pictured / "report.html").read_text()
    assert [int(v) for v in re.findall(r"<h3>Test view (\d+)</h3>", html)] == [0, 4, 7]
    assert "unreadable: " in html and "r_4.png: a damaged or unreadable image file" in html
    assert '<div class="missing">missing</div>' in html


def test_over_scenes_every_variant_is_shown_by_its_run_of_the_same_seed_and_scene(tmp_path):
    # two variants over scenes s1 and s2, seed 0: by path alone variant red's first run ("10" before "9") would be
    # of scene s2 and blue's ("2") of scene s1, pictures of different scenes beside one ground truth
    root = tmp_path / "sweep"
    for name, model, scene, colour in (("9", "red", "s1", RED), ("10", "red", "s2", BLUE), ("2", "blue", "s1", BLUE),
                                       ("3", "blue", "s2", RED)):
        run = make_run(root, name, [f"model={model}", f"data.scene={scene}", "seed=0"])
        add_test_views(run, colour, (0, 0, 0), [20.0] * N_VIEWS)
        results = json.loads((run / "results.json").read_text())
        (run / "results.json").write_text(json.dumps({**results, "config": {"seed": 0}}))
    write_report([root], root, over=("seed", "data.scene"), views=[0])
    html = (root / "report.html").read_text()
    assert html.count("seed 0, data.scene=s1") == 2 and "data.scene=s2" not in html
    renders = [Image.open(root / path).getpixel((0, 0)) for path in re.findall(r'src="([^"]*view0/\d\.png)"', html)]
    assert sorted(renders) == sorted([RED, BLUE])  # each variant's render of scene s1 (of s2: the other colour)
