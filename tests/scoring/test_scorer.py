"""A split with nothing left to score is refused before training, never scored NaN (``check_scored``): masks that
keep no pixel, or none of the pixels the test protocol scores (NeRF-W's right half), and images smaller than SSIM's
window."""

import pytest
import torch

from nerfexp.data.procedural import load_procedural
from nerfexp.data.transforms_file import write_nerfstudio
from nerfexp.data.views import Views
from nerfexp.errors import DatasetError
from nerfexp.nerf.appearance import FULL_IMAGE, NERFW_RIGHT_HALF
from nerfexp.scoring.scorer import check_scored
from tests.helpers import TINY, one_error_line, run_nerfexp

SIZE = 24


def masked(views: Views, keep_columns: slice) -> Views:
    """``views`` with masks that keep the columns ``keep_columns`` of every view but the last, and all of it."""
    mask = torch.zeros(len(views), views.height, views.width, dtype=torch.bool)
    mask[:, :, keep_columns] = True
    mask[-1] = True
    return Views(views.rgba, views.c2w, views.intrinsics, mask=mask)


VIEWS = load_procedural("test", 2, SIZE, SIZE, supersample=1)


def test_a_view_whose_mask_keeps_nothing_is_refused_under_either_protocol():
    nothing = masked(VIEWS, slice(0, 0))
    for protocol in (FULL_IMAGE, NERFW_RIGHT_HALF):
        with pytest.raises(DatasetError, match=r"^the test view 0: (the image|its right half .*) keeps no pixel \(its "
                                               r"mask\), so it would be scored NaN: every view scored must leave "
                                               r"pixels to score$"):
            check_scored(nothing, "test", protocol)
    with pytest.raises(DatasetError, match="^the validation view 0: the image keeps no pixel"):
        check_scored(nothing, "val", FULL_IMAGE)


def test_a_left_half_alone_is_nothing_to_score_under_nerfws_protocol_only():
    left = masked(VIEWS, slice(0, SIZE // 2))  # the first view keeps its left half: what NeRF-W fits, not scores
    check_scored(left, "test", FULL_IMAGE)
    check_scored(left, "val", NERFW_RIGHT_HALF)  # a validation scores the whole image
    with pytest.raises(DatasetError) as caught:
        check_scored(left, "test", NERFW_RIGHT_HALF)
    assert str(caught.value) == ("the test view 0: its right half (columns 12 to 23, test_protocol=nerfw_right_half) "
                                 "keeps no pixel (its mask), so it would be scored NaN: every view scored must leave "
                                 "pixels to score")
    check_scored(masked(VIEWS, slice(SIZE // 2, SIZE)), "test", NERFW_RIGHT_HALF)  # a right half to score


def test_images_smaller_than_ssims_window_are_refused():
    small = load_procedural("test", 1, 12, 20, supersample=1)  # 20 wide: a right half of 10 columns
    check_scored(small, "test", FULL_IMAGE)
    with pytest.raises(DatasetError, match=r"its right half \(columns 10 to 19, .*\) is 10x12 pixels, smaller than "
                                           r"SSIM's 11x11 window"):
        check_scored(small, "test", NERFW_RIGHT_HALF)


def test_a_run_whose_test_views_are_all_masked_out_stops_before_training_in_one_line(tmp_path):
    # the case: every test pixel masked out scored PSNR and SSIM NaN, exit status 0
    views = {split: load_procedural(split, n, SIZE, SIZE, supersample=1)
             for split, n in (("train", 6), ("val", 1), ("test", 2))}
    views["test"].mask = torch.zeros(2, SIZE, SIZE, dtype=torch.bool)
    write_nerfstudio(tmp_path / "scene", views.items())
    tiny = [o for o in TINY if not o.startswith(("data.n_test", "scale.image_size"))]  # the built-in scene's keys
    run_dir = tmp_path / "run"
    result = run_nerfexp("data=nerfstudio", f"data.root={tmp_path / 'scene'}", "data.near=2", "data.far=6", *tiny,
                         "data.n_train=6", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert one_error_line(result) == (f"nerfexp: error: the test view {tmp_path / 'scene' / 'transforms.json'}: frame "
                                      "7 (images/test_0000.png): the image keeps no pixel (its mask), so it would be "
                                      "scored NaN: every view scored must leave pixels to score")
    assert not (run_dir / "results.json").exists() and not (run_dir / "checkpoints").exists()
