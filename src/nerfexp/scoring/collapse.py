"""What counts as a render of nothing: a view whose render is empty or one colour, whatever opacity its rays keep.

A render's ``contrast`` is the spread of its colours about their mean colour (``colour_spread``: the root mean
square distance in RGB, on the 8-bit image the run writes and scores) as a fraction of its target's: 0 for an
image of one colour, about 1 for a render as varied as its target. An empty field renders the background, one
colour; a field that keeps a little opacity everywhere renders the background tinted the same way at every
pixel. Either way the render's colours hardly spread, and opacity alone cannot tell (an even fog of a few percent
opacity shows nothing, and is far above any "empty" threshold on opacity).

A view *rendered nothing* where its contrast is below ``BLANK_CONTRAST``; a view whose target is one colour has
no contrast (NaN): there was nothing to render, so it shows neither way. A set of views (a validation's, the test
split's) rendered nothing where each view that shows anything did (``blank_views``). The guard acts on the
validation views (``nerfexp.training.guards.TrainingGuard``); ``results.json`` and ``eval.json`` record the test
views' verdict (``nerfexp.training.recorders``).
"""

import math

import torch
from torch import Tensor

from nerfexp.pixels import levels

# 1 % of the target's spread: for a target whose colours spread by half the range, about one 8-bit level (1/255),
# the least a PNG can show. A run that is learning renders far more from its first steps: its initial fog already
# follows the rays' lengths through the scene, and its early renders keep several percent of the target's spread
# (tests/scoring/test_collapse.py checks those of a 60-step run on the built-in scene).
BLANK_CONTRAST = 0.01


def colour_spread(image: Tensor, mask: Tensor | None = None) -> float:
    """How far the colours of ``image`` [H, W, 3] (in [0, 1], quantized to 8 bits as ``nerfexp.pixels.quantize``)
    lie from their mean colour: sqrt(mean_p ||c_p - mean c||^2) over the pixels ``mask`` [H, W] keeps (None: all).
    0 for an image of one colour, exactly (the sums are of whole 8-bit levels, exact in float64); half black, half
    white: sqrt(3) / 2. NaN where no pixel is kept."""
    colours = levels(image.double()).reshape(-1, 3)  # [P, 3] whole levels in [0, 255]
    if mask is not None:
        colours = colours[mask.reshape(-1).to(colours.device)]
    if not len(colours):
        return math.nan
    return float(torch.linalg.vector_norm(colours - colours.mean(0), dim=-1).square().mean().sqrt()) / 255


def contrast(render: Tensor, target: Tensor, mask: Tensor | None = None) -> float:
    """The ``colour_spread`` of ``render`` as a fraction of that of ``target`` (both [H, W, 3], over the pixels
    ``mask`` [H, W] keeps): 0 for a render of one colour, 1 for one whose colours spread as the target's do. NaN
    where the target is one colour (or no pixel is kept): it shows nothing a render could miss."""
    target_spread = colour_spread(target, mask)
    if not target_spread > 0:  # 0, or NaN where no pixel is kept
        return math.nan
    return colour_spread(render, mask) / target_spread


def rendered_nothing(view_contrast: float) -> bool:
    """Whether a view whose render has ``view_contrast`` (``contrast``) rendered nothing: below ``BLANK_CONTRAST``
    (a NaN, a target of one colour, never is)."""
    return view_contrast < BLANK_CONTRAST


def blank_views(contrasts: dict[int, float], split: str) -> str | None:
    """Where every view of ``split`` ("validation", "test") whose target shows anything rendered nothing, given
    each view's ``contrast`` by its index, how it did, e.g. "every test view rendered nothing (2 views: an empty
    or one-colour image each, its colours' spread at most 0.3% of its target's, below 1%)"; None where a view
    rendered something, or no view's target shows anything."""
    shown = [value for value in contrasts.values() if not math.isnan(value)]
    if not shown or not all(rendered_nothing(value) for value in shown):
        return None
    one_colour = len(contrasts) - len(shown)
    also = f", besides {one_colour} whose target is one colour" if one_colour else ""
    return (f"every {split} view rendered nothing ({len(shown)} view{'s' if len(shown) > 1 else ''}{also}: an empty "
            f"or one-colour image each, its colours' spread at most {max(shown):.1%} of its target's, below "
            f"{BLANK_CONTRAST:.0%})")
