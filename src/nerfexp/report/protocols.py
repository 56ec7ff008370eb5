"""Which test protocol made each run's scores (``results.json``'s ``test_protocol``: the whole image, or NeRF-W's
right half with the image's appearance code fitted on its left half, ``nerfexp.nerf.appearance``; and its
``test_cameras``: given, or refined with the networks frozen), and the scores the report compares: the runs' own
where they share a protocol; else the right halves every run scored (``test_psnr_right_half``,
``test_ssim_right_half``), said so in the report; a run without them is refused, as are runs whose test cameras
differ (no pixels are scored alike there).

A score's whole protocol, for setting it beside a published one (``Protocol``): the test images' resolution, the
test views scored and how the split chose them, the training steps, and the pixels above (``run_protocol``).
"""

from dataclasses import dataclass, replace

from nerfexp.nerf.appearance import FULL_IMAGE, NERFW_RIGHT_HALF
from nerfexp.report.lpips_weights import without_lpips
from nerfexp.report.runs import Run
from nerfexp.rundir.records import GIVEN, REFINED, is_scored

RIGHT_HALF_KEYS = {"test_psnr": "test_psnr_right_half", "test_ssim": "test_ssim_right_half"}
WORDS = {FULL_IMAGE: "the full-image protocol (each whole test image)",
         NERFW_RIGHT_HALF: "NeRF-W's protocol (the right half of each test image, its appearance code fitted on the "
                           "left half with the networks frozen)"}


def test_protocol(results: dict) -> str:
    """The protocol of a run's headline test scores; full_image for a run of a nerfexp before the key."""
    return results.get("test_protocol", FULL_IMAGE)


def test_cameras(results: dict) -> str:
    """How a run's test images were seen: "given" (as the data gives the cameras; a run of a nerfexp before the
    key) or "refined" (each camera refined with the networks frozen, ``test_cameras=refined``)."""
    return results.get("test_cameras", GIVEN)


def camera_sentence(finished: list[Run]) -> str:
    """A sentence for report.md where the finished runs' test cameras were refined ("" where given); SystemExit in
    one line where some were and some were not: a refined camera sees the image better whatever the model, so
    such scores do not compare."""
    kinds = sorted({test_cameras(run.results) for run in finished})
    if len(kinds) > 1:
        given = next(run for run in finished if test_cameras(run.results) == GIVEN)
        refined = next(run for run in finished if test_cameras(run.results) != GIVEN)
        raise SystemExit(f"nerfexp-report: error: the runs' test cameras differ ({given.path} given, {refined.path} "
                         "refined with the networks frozen): a refined camera raises any model's score; report "
                         "them apart or train them with the same test_cameras")
    if kinds == [REFINED]:
        return ("Each test camera was refined with the networks frozen before its image was scored "
                "(test_cameras=refined).")
    return ""


def compared_runs(runs: list[Run]) -> tuple[list[Run], str]:
    """The runs with the test scores the report compares, and a sentence for report.md saying which they are
    ("" where every run scored the whole image, as nerfexp always did). Where finished runs' headline scores come
    from different protocols, every finished run's ``test_psnr`` and ``test_ssim`` become its right half's (the
    pixels both protocols score; LPIPS, scored under the headline protocol, is left out); a run without them
    stops the report in one line (SystemExit)."""
    finished = [run for run in runs if run.state == "finished"]
    cameras = camera_sentence(finished)
    compared, said = compared_protocols(runs, finished)
    return compared, " ".join(part for part in (said, cameras) if part)


def compared_protocols(runs: list[Run], finished: list[Run]) -> tuple[list[Run], str]:
    """``compared_runs`` for the protocols alone (the pixels scored)."""
    protocols = sorted({test_protocol(run.results) for run in finished})
    if len(protocols) <= 1:
        if protocols in ([], [FULL_IMAGE]):
            return runs, ""
        return runs, f"Test scores are under {WORDS.get(protocols[0], protocols[0])}."
    lacking = [run for run in finished
               if not all(is_scored(run.results.get(key)) for key in RIGHT_HALF_KEYS.values())]
    if lacking:
        raise SystemExit(f"nerfexp-report: error: the runs' test scores come from different protocols "
                         f"({', '.join(protocols)}) and {lacking[0].path} has no right-half scores "
                         f"({RIGHT_HALF_KEYS['test_psnr']}, finite numbers) to compare them on; report them apart")
    compared = [replace(run, results=right_halves(run.results)) if run.state == "finished" else run for run in runs]
    return compared, (f"The runs' headline test scores come from different protocols ({', '.join(protocols)}): every "
                      "test score here is over the right half of each test image (test_psnr_right_half, "
                      "test_ssim_right_half), the pixels both score; LPIPS is left out.")


def right_halves(results: dict) -> dict:
    """A run's ``results`` whose test PSNR and SSIM are its right half's (``RIGHT_HALVES`` says so), without LPIPS."""
    halves = {key: results[half] for key, half in RIGHT_HALF_KEYS.items()}
    return {**without_lpips(results), **halves, RIGHT_HALVES: True}


RIGHT_HALVES = "right_halves_compared"  # a key right_halves adds to the results it makes (never in a file's)
OWN_SPLIT = None  # a Protocol's split where the scene's own files name the test views (no results.json ``split``)
SPLIT_WORDS = "the scene's own test split"


@dataclass(frozen=True)
class Protocol:
    """How test scores were measured: the test images' ``resolution`` (width, height; None: not recorded), the number
    of test ``views`` scored on each scene (lowest, highest; None: not recorded, or for a published protocol every
    view its split holds out), how the ``split`` chose them (results.json's ``split``; ``OWN_SPLIT``: the scene's own
    files), the training ``steps`` (lowest, highest; None: not recorded) and the ``pixels`` scored (the test protocol
    and the test cameras, ``test_protocol`` and ``test_cameras``, or right halves compared: ``pixels_of``)."""

    resolution: tuple[int, int] | None
    views: tuple[int, int] | None
    split: str | None
    steps: tuple[int, int] | None
    pixels: str = FULL_IMAGE

    def covers(self, measured: "Protocol") -> bool:
        """Whether scores ``measured`` so were measured under this (published) protocol: the same resolution, split
        and pixels, as many views (any, where this one takes every view its split holds out) and steps within
        this one's."""
        return (measured.resolution is not None and measured.resolution == self.resolution
                and measured.split == self.split and measured.pixels == self.pixels
                and (self.views is None or measured.views == self.views)
                and measured.steps is not None and self.steps is not None
                and self.steps[0] <= measured.steps[0] and measured.steps[1] <= self.steps[1])

    def text(self, published: bool = False) -> str:
        """In words: "800 x 800 px, 200 test views (the scene's own test split), 100,000 to 300,000 steps";
        ``published``: views None are every view the split holds out (else: not recorded)."""
        size = "resolution not recorded" if self.resolution is None else "{} x {} px".format(*self.resolution)
        if self.views is None:
            views = "every held-out view" if published else "test views not recorded"
        else:
            views = f"{span_text(self.views)} test view{'' if self.views == (1, 1) else 's'}"
        steps = "steps not recorded" if self.steps is None else f"{span_text(self.steps)} steps"
        pixels = "" if self.pixels == FULL_IMAGE else f", {PIXEL_WORDS.get(self.pixels, self.pixels)}"
        return f"{size}, {views} ({SPLIT_WORDS if self.split is OWN_SPLIT else self.split}), {steps}{pixels}"


PIXEL_WORDS = {NERFW_RIGHT_HALF: "NeRF-W's right halves", RIGHT_HALVES: "the right halves of the images",
               REFINED: "test cameras refined"}


def span_text(span: tuple[int, int]) -> str:
    """(200, 200) -> "200"; (100000, 300000) -> "100,000 to 300,000"."""
    return f"{span[0]:,}" if span[0] == span[1] else f"{span[0]:,} to {span[1]:,}"


def pixels_of(results: dict) -> str:
    """The pixels a run's compared scores are of: ``RIGHT_HALVES`` where the report compares right halves, else
    its test protocol, or ``REFINED`` where its test cameras were refined."""
    if results.get(RIGHT_HALVES):
        return RIGHT_HALVES
    return REFINED if test_cameras(results) == REFINED else test_protocol(results)


def run_protocol(results: dict) -> Protocol:
    """The ``Protocol`` a finished run's ``results`` were measured under (its ``test_resolution``, the number of its
    ``test_views``, its ``split``, ``steps`` and ``pixels_of``)."""
    size, views, steps = results.get("test_resolution"), results.get("test_views"), results.get("steps")
    return Protocol(None if size is None else (size[0], size[1]), None if views is None else (len(views), len(views)),
                    results.get("split", OWN_SPLIT), None if steps is None else (steps, steps), pixels_of(results))


def merged_protocol(protocols: list[Protocol]) -> Protocol | None:
    """One protocol for the scores of several runs (a variant's, over seeds or scenes): theirs, with the views and
    steps from their lowest to their highest; None where they differ in anything else, or any is not recorded."""
    first = protocols[0] if protocols else None
    if first is None or any((p.resolution, p.split, p.pixels) != (first.resolution, first.split, first.pixels)
                            or p.views is None or p.steps is None for p in protocols):
        return None
    return replace(first, views=spanned(p.views for p in protocols), steps=spanned(p.steps for p in protocols))


def spanned(spans) -> tuple[int, int]:
    spans = list(spans)
    return min(low for low, _ in spans), max(high for _, high in spans)
