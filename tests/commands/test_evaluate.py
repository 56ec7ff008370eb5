"""``nerfexp-eval``: it replaces the ``eval.json`` it wrote, and never a user's."""

import json
import math
import re
import shutil

import pytest
import torch

from nerfexp import manifest
from nerfexp.commands import evaluate
from tests.helpers import digests


def test_an_evaluation_replaces_its_own_scores_and_refuses_a_users_eval_json(tiny_run, tmp_path, capsys):
    run_dir = shutil.copytree(tiny_run, tmp_path / "run", ignore=shutil.ignore_patterns("eval.json"))
    evaluate.main([str(run_dir)])
    first = json.loads((run_dir / "eval.json").read_text())
    (run_dir / "eval.json").write_text(json.dumps(first))  # rewritten by hand: the same scores, other bytes
    before = digests(run_dir)
    with pytest.raises(SystemExit) as exit:
        evaluate.main([str(run_dir)])
    assert exit.value.code == (
        f"nerfexp-eval: error: {run_dir / 'eval.json'} is not a file nerfexp-eval wrote (it is not in "
        f"{run_dir / manifest.MANIFEST}, or changed since): move it elsewhere: nerfexp-eval writes its scores there")
    assert digests(run_dir) == before  # refused before any work: nothing written

    (run_dir / "eval.json").unlink()
    evaluate.main([str(run_dir)])
    evaluate.main([str(run_dir)])  # its own scores: replaced
    assert manifest.unproven(run_dir, ["eval.json"]) == [] and "written to" in capsys.readouterr().out


def test_a_checkpoint_that_renders_nan_records_no_score(tiny_run, tmp_path):
    # weights of NaN (a checkpoint from elsewhere): no eval.json with a NaN score, one line instead
    run_dir = shutil.copytree(tiny_run, tmp_path / "run", ignore=shutil.ignore_patterns("eval.json"))
    checkpoint = run_dir / "checkpoints" / "last.ckpt"
    content = torch.load(checkpoint, weights_only=True)
    for weights in content["state_dict"].values():
        if weights.is_floating_point():
            weights.fill_(math.nan)
    torch.save(content, checkpoint)
    with pytest.raises(SystemExit) as exit:
        evaluate.main([str(checkpoint)])  # named: the file, not the run's own checkpoint
    line = str(exit.value.code)  # NaN scores refused (image_scores), or weights of NaN where they are read
    assert line.startswith("nerfexp-eval: error: ") and re.search("nan|finite", line, re.I) and "\n" not in line
    assert not (run_dir / "eval.json").exists()
