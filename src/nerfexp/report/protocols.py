"""Which test protocol made each run's scores (``results.json``'s ``test_protocol``: the whole image, or NeRF-W's
right half with the image's appearance code fitted on its left half, ``nerfexp.nerf.appearance``), and the scores
the report compares: the runs' own where they share a protocol; else the right halves every run scored
(``test_psnr_right_half``, ``test_ssim_right_half``), said so in the report; a run without them is refused.
"""

from dataclasses import replace

from nerfexp.nerf.appearance import FULL_IMAGE, NERFW_RIGHT_HALF
from nerfexp.report.runs import Run

RIGHT_HALF_KEYS = {"test_psnr": "test_psnr_right_half", "test_ssim": "test_ssim_right_half"}
WORDS = {FULL_IMAGE: "the full-image protocol (each whole test image)",
         NERFW_RIGHT_HALF: "NeRF-W's protocol (the right half of each test image, its appearance code fitted on the "
                           "left half with the networks frozen)"}


def test_protocol(results: dict) -> str:
    """The protocol of a run's headline test scores; full_image for a run of a nerfexp before the key."""
    return results.get("test_protocol", FULL_IMAGE)


def compared_runs(runs: list[Run]) -> tuple[list[Run], str]:
    """The runs with the test scores the report compares, and a sentence for report.md saying which they are
    ("" where every run scored the whole image, as nerfexp always did). Where finished runs' headline scores come
    from different protocols, every finished run's ``test_psnr`` and ``test_ssim`` become its right half's (the
    pixels both protocols score; LPIPS, scored under the headline protocol, is left out); a run without them
    stops the report in one line (SystemExit)."""
    finished = [run for run in runs if run.state == "finished"]
    protocols = sorted({test_protocol(run.results) for run in finished})
    if len(protocols) <= 1:
        if protocols in ([], [FULL_IMAGE]):
            return runs, ""
        return runs, f"Test scores are under {WORDS.get(protocols[0], protocols[0])}."
    lacking = [run for run in finished if not all(key in run.results for key in RIGHT_HALF_KEYS.values())]
    if lacking:
        raise SystemExit(f"nerfexp-report: error: the runs' test scores come from different protocols "
                         f"({', '.join(protocols)}) and {lacking[0].path} has no right-half scores "
                         f"({RIGHT_HALF_KEYS['test_psnr']}) to compare them on; report them apart")
    compared = [replace(run, results=right_halves(run.results)) if run.state == "finished" else run for run in runs]
    return compared, (f"The runs' headline test scores come from different protocols ({', '.join(protocols)}): every "
                      "test score here is over the right half of each test image (test_psnr_right_half, "
                      "test_ssim_right_half), the pixels both score; LPIPS is left out.")


def right_halves(results: dict) -> dict:
    """A run's ``results`` whose test PSNR and SSIM are its right half's, without LPIPS."""
    halves = {key: results[half] for key, half in RIGHT_HALF_KEYS.items()}
    return {**{key: value for key, value in results.items() if not key.startswith("test_lpips")}, **halves}
