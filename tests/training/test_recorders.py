"""What the recorders make of each image's scores: LPIPS recorded beside PSNR and SSIM where every image has
it, left out (never NaN in a file) where it was not scored, and gathered across processes with them."""

import json
import math
import types

import pytest
import torch

from nerfexp.errors import NonFiniteError
from nerfexp.scoring.metrics import psnr, ssim
from nerfexp.training.recorders import (
    IMAGES,
    collapse_record,
    gather_evaluations,
    image_means,
    image_scores,
    scores_record,
    scores_text,
)

NAN = math.nan


def test_lpips_is_recorded_where_every_image_has_it():
    scores = {3: {"psnr": 20.0, "ssim": 0.5, "lpips": 0.25}, 1: {"psnr": 30.0, "ssim": 0.7, "lpips": 0.125}}
    assert image_means(scores) == {"psnr": 25.0, "ssim": 0.6, "lpips": 0.1875}
    assert scores_record(scores) == {
        "test_psnr": 25.0, "test_ssim": 0.6, "test_lpips": 0.1875, "test_views": [1, 3],
        "test_psnr_per_view": [30.0, 20.0], "test_ssim_per_view": [0.7, 0.5], "test_lpips_per_view": [0.125, 0.25]}
    assert scores_text(scores_record(scores)) == "test PSNR 25.00 dB, SSIM 0.6000, LPIPS 0.1875"


@pytest.mark.parametrize("lpips", [(NAN, NAN), (0.1, NAN)])
def test_lpips_not_scored_for_an_image_is_left_out_of_the_record(lpips):
    scores = {0: {"psnr": 20.0, "ssim": 0.5, "lpips": lpips[0]}, 1: {"psnr": 30.0, "ssim": 0.7, "lpips": lpips[1]}}
    record = scores_record(scores)
    assert record == {"test_psnr": 25.0, "test_ssim": 0.6, "test_views": [0, 1], "test_psnr_per_view": [20.0, 30.0],
                      "test_ssim_per_view": [0.5, 0.7]}
    json.dumps(record, allow_nan=False)  # valid JSON: no NaN anywhere
    assert image_means(scores) == {"psnr": 25.0, "ssim": 0.6}
    assert scores_text(record) == "test PSNR 25.00 dB, SSIM 0.6000"


def test_the_scores_travel_between_processes_as_float64_nan_included():
    def all_gather(tensor):  # two processes that evaluated the same
        return torch.stack([tensor, tensor])

    trainer = types.SimpleNamespace(world_size=2, strategy=types.SimpleNamespace(all_gather=all_gather))
    images = {key: torch.zeros(2, 2, 3) for key in IMAGES}
    for lpips in (0.123456789012345, NAN):
        outputs = {"index": 7, "psnr": 31.234567890123, "ssim": 0.91, "lpips": lpips, **images}
        gathered = gather_evaluations(trainer, outputs)
        assert len(gathered) == 2
        for item in gathered:
            assert (item["index"], item["psnr"], item["ssim"]) == (7, 31.234567890123, 0.91)
            assert item["lpips"] == lpips or (math.isnan(lpips) and math.isnan(item["lpips"]))


def test_an_image_scored_nan_stops_the_run_before_any_mean_is_recorded():
    # LPIPS and the protocols' own scores may be missing (left out of the record); PSNR and SSIM never
    item = {"index": 4, "psnr": 21.5, "ssim": 0.75, "lpips": NAN, "psnr_right_half": NAN}
    scores = image_scores(item, "test", 60)
    assert (scores["psnr"], scores["ssim"]) == (21.5, 0.75) and math.isnan(scores["lpips"])
    for nan, says in ((["psnr"], "psnr"), (["psnr", "ssim"], "psnr and ssim"), (["ssim"], "ssim")):
        with pytest.raises(NonFiniteError) as caught:
            image_scores({**item, **dict.fromkeys(nan, NAN)}, "val", 30)
        assert str(caught.value) == (f"step 30: the validation view 4 scored {says} NaN (its render holds NaN "
                                     "pixels): no score is recorded")


def test_a_render_of_nan_is_scored_nan():
    # what image_scores stops: the scores of a NaN render (weights that are not finite) are NaN, not a number
    image, target = torch.full((16, 16, 3), NAN), torch.rand(16, 16, 3)
    assert math.isnan(psnr(image, target)) and math.isnan(ssim(image, target))


def test_each_views_contrast_travels_with_its_scores_and_decides_the_collapse_record():
    def all_gather(tensor):
        return torch.stack([tensor, tensor])

    trainer = types.SimpleNamespace(world_size=2, strategy=types.SimpleNamespace(all_gather=all_gather))
    images = {key: torch.zeros(2, 2, 3) for key in IMAGES}
    outputs = {"index": 4, "psnr": 14.71, "ssim": 0.5, "lpips": NAN, "contrast": 0.0078125, **images}
    (first, second) = gather_evaluations(trainer, outputs)
    assert first["contrast"] == second["contrast"] == 0.0078125
    blank = {4: image_scores(first, "test", 0), 5: {**image_scores(first, "test", 0), "contrast": 0.0}}
    assert collapse_record(blank) == {"collapse": "every test view rendered nothing (2 views: an empty or one-colour "
                                      "image each, its colours' spread at most 0.8% of its target's, below 1%)"}
    assert collapse_record({**blank, 6: {**image_scores(first, "test", 0), "contrast": 0.25}}) == {"collapse": None}
    assert "contrast" not in image_means(blank) and "test_contrast" not in scores_record(blank)  # not a score
    record = {**scores_record(blank), **collapse_record(blank)}
    assert scores_text(record) == ("test PSNR 14.71 dB, SSIM 0.5000, scores of a render of nothing: every test view "
                                   "rendered nothing (2 views: an empty or one-colour image each, its colours' spread "
                                   "at most 0.8% of its target's, below 1%)")
