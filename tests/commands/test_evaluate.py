"""``nerfexp-eval``: it replaces the ``eval.json`` it wrote, and never a user's."""

import json
import shutil

import pytest

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
