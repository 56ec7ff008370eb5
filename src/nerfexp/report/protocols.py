"""Which test protocol made each run's scores (``results.json``'s ``test_protocol``: the whole image, or NeRF-W's
right half with the image's appearance code fitted on its left half, ``nerfexp.nerf.appearance``; and its
``test_cameras``: given, or refined with the networks frozen), and the scores the report compares: the runs' own
where they share a protocol; else the right halves every run scored (``test_psnr_right_half``,
``test_ssim_right_half``), said so in the report; a run without them is refused, as are runs whose test cameras
differ (no pixels are scored alike there).
"""

from dataclasses import replace

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
    """A run's ``results`` whose test PSNR and SSIM are its right half's, without LPIPS."""
    halves = {key: results[half] for key, half in RIGHT_HALF_KEYS.items()}
    return {**without_lpips(results), **halves}
