"""What one evaluated image measures (``MEASURES``): its scores (``SCORES``: PSNR and SSIM always, LPIPS where scored,
each test protocol's own, the test camera's fit) and its render's contrast, read from an evaluation step's outputs
(``image_scores``) and averaged over the images (``image_means``). The recorders (``nerfexp.training.recorders``)
and the budgets' scoring (``nerfexp.training.budgets``) both read evaluations through these.
"""

import math

import numpy as np

from nerfexp.data.views import SPLIT_NAMES
from nerfexp.errors import NonFiniteError
from nerfexp.scoring.perceptual import LPIPS_NAMES

# each image's scores; lpips (the published weights') or lpips_custom (the user's own), NaN where not scored
# (nerfexp.scoring.perceptual); then each protocol's own, which only a test scores (NaN in a validation:
# ``TestScorer.protocol_scores``, docs/metrics.md)
PROTOCOL_SCORES = ("psnr_full_image", "ssim_full_image", "psnr_right_half", "ssim_right_half")
CAMERA_FIT = ("camera_fit_deg", "camera_fit_shift")  # the test cameras' corrections (test_cameras=refined)
SCORES = ("psnr", "ssim", *LPIPS_NAMES, *PROTOCOL_SCORES, *CAMERA_FIT)
ALWAYS_SCORED = ("psnr", "ssim")
# what each image's evaluation measures: its SCORES, and its render's contrast against its target's, which is no
# score (never averaged or logged) but says whether the view rendered anything (nerfexp.scoring.collapse)
MEASURES = (*SCORES, "contrast")


def image_scores(item: dict, split: str, step: int) -> dict[str, float]:
    """The ``MEASURES`` of one evaluated image (``NeRFModule._evaluate``'s outputs, or an item of
    ``nerfexp.training.recorders.gather_evaluations``) of ``split`` at ``step``, NaN for those it
    was not scored by; a NonFiniteError where its PSNR or SSIM (``ALWAYS_SCORED``) is NaN, so that no mean over
    it is recorded. Every view scored was checked to have pixels to score before the first step
    (``nerfexp.scoring.scorer.check_scored``), so such a score comes from the render: weights or an appearance
    code that render NaN. Every process raises it alike: the items are every process's."""
    scores = {name: item.get(name, math.nan) for name in MEASURES}
    if missing := [name for name in ALWAYS_SCORED if math.isnan(scores[name])]:
        raise NonFiniteError(f"step {step}: the {SPLIT_NAMES[split]} view {item['index']} scored "
                             f"{' and '.join(missing)} NaN (its render holds NaN pixels): no score is recorded")
    return scores


def scored(scores: dict[int, dict[str, float]]) -> tuple[str, ...]:
    """The scores that the images ``{index: {"psnr": ..., "ssim": ..., "lpips": ...}}`` have: PSNR and SSIM,
    and each other of ``SCORES`` where every image has it (none is NaN or missing: not scored, as LPIPS without
    AlexNet's weights, or the protocols' own scores in a validation)."""
    def every_image_has(name: str) -> bool:
        return bool(scores) and not any(math.isnan(s.get(name, math.nan)) for s in scores.values())
    return (*ALWAYS_SCORED, *(name for name in SCORES if name not in ALWAYS_SCORED and every_image_has(name)))


def image_means(scores: dict[int, dict[str, float]]) -> dict[str, float]:
    """Means of per-image scores ``{index: {"psnr": ..., "ssim": ..., "lpips": ...}}``, in image order, of
    those ``scored``: LPIPS left out where it is not."""
    ordered = [scores[index] for index in sorted(scores)]
    return {name: float(np.mean([s[name] for s in ordered])) for name in scored(scores)}
