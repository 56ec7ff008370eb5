"""The report compares test scores made under one protocol (nerfexp.report.protocols): a sweep of appearance=none,
embedding on the right halves both scored, said so; runs without right-half scores refused in one line."""

import csv
import json
from pathlib import Path

import pytest

from nerfexp.report.folder import write_report
from tests.helpers import make_run, one_error_line, run_nerfexp


def appearance_run(root: Path, name: str, appearance: str, seed: int, full: float, right: float) -> Path:
    """A finished run of ``appearance`` (none: the full image's protocol; embedding: NeRF-W's) whose whole image
    scored ``full`` dB and right half ``right`` dB (SSIM: the PSNR / 100)."""
    run = make_run(root, name, [f"appearance={appearance}", f"seed={seed}"], psnr=full, ssim=full / 100,
                   lpips=0.1)
    results = json.loads((run / "results.json").read_text())
    protocol = "full_image" if appearance == "none" else "nerfw_right_half"
    headline = full if appearance == "none" else right
    results.update(test_protocol=protocol, test_psnr=headline, test_ssim=headline / 100,
                   test_psnr_full_image=full, test_ssim_full_image=full / 100,
                   test_psnr_right_half=right, test_ssim_right_half=right / 100)
    (run / "results.json").write_text(json.dumps(results))
    return run


def test_a_sweep_of_both_protocols_is_compared_on_the_right_halves_and_says_so(tmp_path):
    for seed, (none_right, embedding_right) in enumerate([(20.0, 21.0), (20.5, 21.3)]):
        appearance_run(tmp_path, f"n{seed}", "none", seed, full=30.0, right=none_right)
        appearance_run(tmp_path, f"e{seed}", "embedding", seed, full=18.0, right=embedding_right)
    write_report([tmp_path], tmp_path, reference="appearance=none")
    rows = {row["variant"]: row for row in csv.DictReader((tmp_path / "report.csv").open())}
    assert float(rows["appearance=none"]["test_psnr_mean"]) == pytest.approx(20.25)  # right halves, not 30
    assert float(rows["appearance=embedding"]["test_psnr_mean"]) == pytest.approx(21.15)
    assert float(rows["appearance=embedding"]["psnr_diff"]) == pytest.approx(0.9)  # (1.0 + 0.8) / 2, paired
    assert rows["appearance=none"]["test_lpips_mean"] == "nan"  # another protocol's pixels: left out
    report = (tmp_path / "report.md").read_text()
    assert "different protocols (full_image, nerfw_right_half)" in report
    assert "right half of each test image" in report


def test_runs_of_one_protocol_keep_their_own_scores(tmp_path):
    appearance_run(tmp_path, "e0", "embedding", 0, full=18.0, right=21.0)
    write_report([tmp_path], tmp_path)
    rows = list(csv.DictReader((tmp_path / "report.csv").open()))
    assert float(rows[0]["test_psnr_mean"]) == 21.0
    assert "under NeRF-W's protocol" in (tmp_path / "report.md").read_text()


def test_runs_without_right_half_scores_under_another_protocol_are_refused_in_one_line(tmp_path):
    make_run(tmp_path, "old", ["appearance=none", "seed=0"], psnr=30.0)  # an earlier nerfexp's: no protocol keys
    appearance_run(tmp_path, "e0", "embedding", 0, full=18.0, right=21.0)
    result = run_nerfexp(str(tmp_path), cwd=tmp_path, script="nerfexp-report")
    assert result.returncode != 0
    line = one_error_line(result, "nerfexp-report")
    assert "different protocols (full_image, nerfw_right_half)" in line and "old has no right-half scores" in line


def camera_run(root: Path, name: str, seed: int, cameras: str | None) -> Path:
    """A finished run of the default protocol whose test cameras were ``cameras`` (None: a nerfexp before the key)."""
    run = make_run(root, name, [f"camera_opt={'so3xr3' if name.startswith('r') else 'off'}", f"seed={seed}"],
                   psnr=25.0 + seed, ssim=0.8, lpips=0.1)
    if cameras is not None:
        results = json.loads((run / "results.json").read_text())
        (run / "results.json").write_text(json.dumps({**results, "test_cameras": cameras}))
    return run


def test_runs_whose_test_cameras_were_refined_are_reported_as_such(tmp_path):
    for seed in (0, 1):
        camera_run(tmp_path, f"o{seed}", seed, "refined")
        camera_run(tmp_path, f"r{seed}", seed, "refined")
    write_report([tmp_path], tmp_path, reference="camera_opt=off")
    assert "refined with the networks frozen before its image was scored" in (tmp_path / "report.md").read_text()


@pytest.mark.parametrize("given", ["given", None])
def test_runs_with_refined_and_given_test_cameras_are_refused_in_one_line(tmp_path, given):
    camera_run(tmp_path, "o0", 0, given)
    camera_run(tmp_path, "r0", 0, "refined")
    result = run_nerfexp(str(tmp_path), cwd=tmp_path, script="nerfexp-report")
    assert result.returncode != 0
    line = one_error_line(result, "nerfexp-report")
    assert "test cameras differ" in line and "o0 given" in line and "r0 refined" in line
