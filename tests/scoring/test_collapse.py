"""What counts as a render of nothing (``nerfexp.scoring.collapse``), against hand-worked images and the renders of
real runs: an empty or one-colour render is caught whatever opacity its rays keep; a run that is learning is not."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from nerfexp.scoring.collapse import BLANK_CONTRAST, blank_views, colour_spread, contrast, rendered_nothing

LEVEL = 1 / 255  # one step of an 8-bit image


def halves(left: tuple, right: tuple, size: int = 4) -> torch.Tensor:
    """A [size, 2 size, 3] image: colour ``left`` on its left half, ``right`` on its right half."""
    image = torch.empty(size, 2 * size, 3)
    image[:, :size], image[:, size:] = torch.tensor(left), torch.tensor(right)
    return image


def test_the_spread_of_known_images():
    assert colour_spread(torch.full((5, 7, 3), 0.3)) == 0.0
    # half black, half white: the mean colour is grey (0.5, 0.5, 0.5), every pixel sqrt(3) / 2 from it
    assert colour_spread(halves((0, 0, 0), (1, 1, 1))) == pytest.approx(math.sqrt(3) / 2, abs=1e-12)
    # half red, half green: mean (0.5, 0.5, 0), every pixel sqrt(0.5^2 + 0.5^2) = sqrt(2) / 2 from it
    assert colour_spread(halves((1, 0, 0), (0, 1, 0))) == pytest.approx(math.sqrt(2) / 2, abs=1e-12)
    left = torch.zeros(4, 8, dtype=torch.bool)
    left[:, :4] = True
    assert colour_spread(halves((0, 0, 0), (1, 1, 1)), left) == 0.0  # the kept pixels are all black
    assert math.isnan(colour_spread(halves((0, 0, 0), (1, 1, 1)), torch.zeros(4, 8, dtype=torch.bool)))


def test_the_spread_is_that_of_the_8_bit_image():
    # pixels that differ by less than half a level are one colour in the PNG the run writes: no spread
    faint = halves((1, 1, 1), (1 - 0.4 * LEVEL,) * 3)
    assert colour_spread(faint) == 0.0
    # a whole level apart: half the pixels one level darker, sqrt(3) / 2 levels from the mean in RGB
    assert colour_spread(halves((1, 1, 1), (1 - LEVEL,) * 3)) == pytest.approx(math.sqrt(3) / 2 * LEVEL, rel=1e-9)


def test_contrast_of_known_renders():
    target = halves((0, 0, 0), (1, 1, 1))
    assert contrast(torch.ones(4, 8, 3), target) == 0.0  # white everywhere: an empty scene on a white background
    assert contrast(target, target) == pytest.approx(1.0)
    # the scene kept at 5% opacity on white: pixels 0.95 (242.25, stored as 242) and 1 (255), 13 levels apart where
    # the target's are 255: the same geometry, 13 / 255 of the spread
    fogged = 0.05 * target + 0.95
    assert contrast(fogged, target) == pytest.approx(13 / 255, abs=1e-12)
    assert math.isnan(contrast(target, torch.full((4, 8, 3), 0.5)))  # a one-colour target shows nothing to miss


images = st.integers(2, 6).flatmap(lambda h: st.integers(2, 6).flatmap(lambda w: st.lists(
    st.floats(0, 1, allow_nan=False), min_size=h * w * 3, max_size=h * w * 3).map(
        lambda values: torch.tensor(values, dtype=torch.float64).reshape(h, w, 3))))


@settings(max_examples=60, deadline=None)
@given(images, st.floats(0, 1), st.floats(0, 1), st.floats(0, 1))
def test_contrast_is_that_of_the_render_to_its_target(target, r, g, b):
    spread = colour_spread(target)
    if spread == 0:
        assert math.isnan(contrast(target, target))
        return
    assert contrast(target, target) == pytest.approx(1.0, abs=1e-12)
    one_colour = torch.tensor([r, g, b], dtype=torch.float64).expand_as(target)
    assert contrast(one_colour, target) == 0.0  # whatever colour, whatever opacity made it
    assert rendered_nothing(contrast(one_colour, target)) and not rendered_nothing(contrast(target, target))


@settings(max_examples=60, deadline=None)
@given(images, st.data())
def test_pixels_a_mask_leaves_out_do_not_count(target, data):
    H, W, _ = target.shape
    keep = torch.tensor(data.draw(st.lists(st.booleans(), min_size=H * W, max_size=H * W))).reshape(H, W)
    render = target.clone()
    render[~keep] = 1 - render[~keep]  # changed only where the mask does not look
    other = target.clone()
    other[~keep] = 0.5
    if not keep.any():  # nothing kept: nothing to judge
        assert math.isnan(colour_spread(render, keep)) and math.isnan(contrast(render, other, keep))
        return
    assert colour_spread(render, keep) == colour_spread(target, keep)
    a, b = contrast(render, other, keep), contrast(target, target, keep)
    assert (math.isnan(a) and math.isnan(b)) or a == pytest.approx(b, abs=1e-12)


@given(st.dictionaries(st.integers(0, 100), st.floats(0, BLANK_CONTRAST, exclude_max=True), min_size=1),
       st.dictionaries(st.integers(101, 200), st.just(math.nan)))
def test_views_that_all_rendered_nothing_are_said(blank, one_colour_targets):
    line = blank_views({**blank, **one_colour_targets}, "test")
    assert line is not None and line.startswith(f"every test view rendered nothing ({len(blank)} view")
    assert f"at most {max(blank.values()):.1%} of its target's" in line
    assert ("whose target is one colour" in line) == bool(one_colour_targets)


@given(st.dictionaries(st.integers(0, 100), st.floats(0, 1), min_size=1), st.floats(BLANK_CONTRAST, 10))
def test_one_view_that_rendered_something_clears_them_all(views, shown):
    assert blank_views({**views, 101: shown}, "validation") is None


def test_views_whose_targets_show_nothing_say_nothing():
    assert blank_views({}, "test") is None
    assert blank_views({0: math.nan, 1: math.nan}, "test") is None
    assert blank_views({0: 0.0, 3: 0.004}, "validation") == (
        "every validation view rendered nothing (2 views: an empty or one-colour image each, its colours' spread at "
        "most 0.4% of its target's, below 1%)")


def png(path) -> torch.Tensor:
    return torch.from_numpy(np.asarray(Image.open(path).convert("RGB"), dtype=np.float64) / 255)


def test_a_learning_runs_renders_are_far_from_nothing(tiny_run):
    # the TINY run's test renders after 60 steps, a field just past its first fog: read back from the PNGs it wrote
    for view in (0, 1):
        render, target = png(tiny_run / "test" / f"r_{view}.png"), png(tiny_run / "test" / f"r_{view}_target.png")
        assert contrast(render, target) > 5 * BLANK_CONTRAST
