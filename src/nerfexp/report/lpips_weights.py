"""Which runs' LPIPS the report tables: only what nerfexp can vouch for, scores of torchvision's published AlexNet
weights, which a run's ``results.json`` shows by their SHA-256 (``lpips_weights_sha256`` equal to
``nerfexp.scoring.perceptual.ALEXNET_SHA256``). A run's ``test_lpips`` without it (a run of an earlier nerfexp,
which recorded no digest, or one whose file says other weights) is left out of the tables, the comparisons and the
captions, and report.md says whose. Scores of a user's own weights (``test_lpips_custom``) are never tabled: they
are not LPIPS and compare with nothing.
"""

from dataclasses import replace

from nerfexp.report.runs import Run
from nerfexp.scoring.perceptual import ALEXNET_SHA256

LPIPS_KEYS = "test_lpips"  # the start of every LPIPS key of results.json: test_lpips, _per_view, _custom


def without_lpips(results: dict) -> dict:
    """A run's ``results`` without any of its LPIPS scores (``LPIPS_KEYS``)."""
    return {key: value for key, value in results.items() if not key.startswith(LPIPS_KEYS)}


def vouched(results: dict) -> bool:
    """Whether a run's ``results`` hold no LPIPS, or LPIPS of the published weights (their SHA-256 recorded)."""
    return "test_lpips" not in results or results.get("lpips_weights_sha256") == ALEXNET_SHA256


def vouched_lpips(runs: list[Run]) -> tuple[list[Run], str]:
    """The ``runs`` with the LPIPS of finished runs that do not show the published weights' digest (``vouched``)
    left out, and a sentence for report.md naming those runs ("" where there are none)."""
    def left_out(run: Run) -> bool:
        return run.state == "finished" and not vouched(run.results)

    unvouched = [run for run in runs if left_out(run)]
    if not unvouched:
        return runs, ""
    kept = [replace(run, results=without_lpips(run.results)) if left_out(run) else run for run in runs]
    named = ", ".join(f"`{run.path}`" for run in unvouched)
    return kept, (f"The LPIPS of {len(unvouched)} run(s) is left out ({named}): "
                  "their results.json does not show torchvision's published AlexNet weights by their SHA-256 "
                  "(lpips_weights_sha256; a run of an earlier nerfexp, or other weights), so nerfexp cannot vouch "
                  "that it is LPIPS (docs/metrics.md).")
