"""The paper's successors on its axes, through the real config and the command line: proposal sampling as a
third choice beside the hierarchy and Ref-NeRF's view dependence beside the paper's head, in one sweep,
reported together, and read back by the evaluation."""

import csv
import math

import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from tests.helpers import TINY, read_json, run_nerfexp

# the proposal rounds sized as the TINY hierarchy: 16 + 16 proposal samples and 16 for the field, as many
# samples per ray as its 16 + (16 + 16) (in a sweep each job leaves the other choice's counts unused)
PROPOSAL = ["proposal.n_samples=[16,16]", "proposal.n_final=16", "proposal.network.width=16"]


@pytest.mark.slow
def test_proposal_sampling_and_reflections_sweep_beside_the_papers_choices(tmp_path):
    sweep = tmp_path / "sweep"
    result = run_nerfexp("-m", *TINY, *PROPOSAL, "hierarchical=true,proposal", "view_dependence=mlp,ref",
                         f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    runs = {}
    for path in sweep.glob("*/results.json"):
        r = read_json(path)
        runs[r["choices"]["hierarchical"], r["choices"]["view_dependence"]] = (path.parent, r)
    results = {key: r for key, (_, r) in runs.items()}
    assert set(results) == {(True, "mlp"), (True, "ref"), ("proposal", "mlp"), ("proposal", "ref")}
    for (hierarchical, view), r in results.items():
        assert math.isfinite(r["test_psnr"]) and r["evaluations_per_ray"] == 48
        tags = set(EventAccumulator(str(runs[hierarchical, view][0] / "tensorboard")).Reload().Tags()["scalars"])
        assert ("train/interlevel" in tags) == (hierarchical == "proposal"), (hierarchical, view)
        assert ({"train/normals", "train/orientation"} <= tags) == (view == "ref"), (hierarchical, view)
        # the unused counts are recorded as null: the hierarchy's sample counts in a proposal job, and back
        unused = ["n_coarse", "n_fine"] if hierarchical == "proposal" else []
        assert all(r["config"]["scale"][k] is None for k in unused)
        if hierarchical is True:
            assert r["config"]["proposal"]["n_final"] is None

    report = run_nerfexp(str(sweep), cwd=tmp_path, script="nerfexp-report")
    assert report.returncode == 0, report.stderr[-3000:]
    with open(sweep / "report.csv") as file:
        variants = {row["variant"] for row in csv.DictReader(file)}
    assert variants == {f"hierarchical={h}, view_dependence={v}" for h in ("True", "proposal") for v in ("mlp", "ref")}

    # a run of both successors is read back from its directory alone: the evaluation scores what it tested
    run_dir = runs["proposal", "ref"][0]
    evaluation = run_nerfexp(str(run_dir), cwd=tmp_path, script="nerfexp-eval")
    assert evaluation.returncode == 0, evaluation.stderr[-3000:]
    assert read_json(run_dir / "eval.json")["test_psnr"] == pytest.approx(
        results["proposal", "ref"]["test_psnr"], abs=1e-4)
