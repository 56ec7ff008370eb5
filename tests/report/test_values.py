"""nerfexp-report over runs whose records hold values of the wrong type, not finite or out of range: each such run
is damaged (naming the file, the key and the value), collapsed or not scored, and never ranked or compared; the
runs that are as nerfexp writes them are reported as ever. The same records read by nerfexp-eval and nerfexp's
claim on a run directory are one line."""

import csv
import json
import math
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nerfexp.errors import NerfexpError
from nerfexp.report.folder import write_report
from nerfexp.report.runs import read_run
from nerfexp.rundir.claim import admit_run, held_run
from nerfexp.rundir.records import PSNR_LIMIT, RESULTS_FIELDS
from nerfexp.rundir.trained import find_run, read_refined_poses
from tests.helpers import make_run

# the highest finite PSNR of 8-bit images of 3 (2^63 - 1) channels, one level off in one channel, by hand:
# -10 log10((1/255)^2 / (3 (2^63 - 1))) = 20 log10(255) + 10 log10(3) + 10 log10(2^63 - 1) = 48.13 + 4.77 + 189.65
assert math.isclose(PSNR_LIMIT, 242.55, abs_tol=0.01)


def edit(path: Path, **changes) -> None:
    """Set ``changes`` in the JSON file ``path``; a value ``...`` removes the key."""
    record = json.loads(path.read_text())
    record.update(changes)
    path.write_text(json.dumps({key: value for key, value in record.items() if value is not ...}))


# a field of results.json the report reads, a value nerfexp never writes there, and how the report names it
ODD_RESULTS = [
    ("test_cameras", None, "key 'test_cameras' is None: expected one of given, refined"),
    ("test_cameras", ["given"], "key 'test_cameras' is ['given']: expected one of given, refined"),
    ("test_protocol", None, "key 'test_protocol' is None: expected one of full_image, nerfw_right_half"),
    ("test_protocol", [], "key 'test_protocol' is []: expected one of full_image, nerfw_right_half"),
    ("test_psnr_right_half", "31.2", "key 'test_psnr_right_half' is '31.2': expected a number in [0, 242.55"),
    ("test_ssim_right_half", 2.0, "key 'test_ssim_right_half' is 2.0: expected a number in [-1, 1]"),
    ("test_psnr", "22", "key 'test_psnr' is '22': expected a number in [0, 242.55"),
    ("test_psnr", 1e300, "key 'test_psnr' is 1e+300: expected a number in [0, 242.55"),
    ("test_ssim", -3, "key 'test_ssim' is -3: expected a number in [-1, 1]"),
    ("test_lpips", math.nan, "key 'test_lpips' is nan: expected a finite number >= 0 and <= 2^63 - 1"),
    ("train_time_s", 1e308, "key 'train_time_s' is 1e+308: expected a finite number >= 0 and <= 2^63 - 1"),
    ("n_params", "1000", "key 'n_params' is '1000': expected a whole number in [0, 2^63 - 1]"),
    ("choices", {"encoding": ["posenc"]}, "key 'choices' is {'encoding': ['posenc']}: expected a mapping"),
    ("machine", "lab-pc", "key 'machine' is 'lab-pc': expected a mapping of texts host and device"),
    ("machine", {"host": "lab-pc"}, "key 'machine' is {'host': 'lab-pc'}: expected a mapping of texts host and"),
    ("config", {"trainer": [1]}, "key 'config.trainer' is [1]: expected a mapping"),
    ("test_views", [0, 1], "key 'test_psnr_per_view' has 1 items for 2 test_views"),
    ("collapse", ["step 9"], "key 'collapse' is ['step 9']: expected a text of one line, or null"),
    ("precision", 32, "key 'precision' is 32: expected a text"),
    ("lpips_weights_sha256", "7be5be79", "key 'lpips_weights_sha256' is '7be5be79': expected 64 hexadecimal digits"),
    ("test_lpips_custom", -0.5, "key 'test_lpips_custom' is -0.5: expected a finite number >= 0"),
    ("test_lpips_custom_per_view", [0.1, 0.2], "key 'test_lpips_custom_per_view' has 2 items for 1 test_views"),
]


@pytest.mark.parametrize(("key", "value", "says"), ODD_RESULTS, ids=[f"{k}={v!r}" for k, v, _ in ODD_RESULTS])
def test_a_results_field_not_as_nerfexp_writes_it_makes_the_run_damaged_naming_the_key(tmp_path, key, value, says):
    run = make_run(tmp_path, "0", ["seed=0"])
    edit(run / "results.json", **{"test_views": [0], "test_psnr_per_view": [20.0], key: value})
    read = read_run(run)
    assert (read.state, read.overrides) == ("damaged", ["seed=0"]) and read.results is None
    assert read.detail.startswith("results.json: ") and says in read.detail and "\n" not in read.detail, read.detail


@pytest.mark.parametrize(("file", "key", "value", "says"), [
    ("status.json", "state", ["finished"], "status.json: key 'state' is ['finished']: expected one of running"),
    ("status.json", "pid", "1234", "status.json: key 'pid' is '1234': expected a whole number in [1, 2147483647]"),
    ("status.json", "pid", 2 ** 70, "status.json: key 'pid' is 1180591620717411303424: expected a whole number"),
    ("status.json", "overrides", [1, 2], "status.json: key 'overrides' is [1, 2]: expected a list of items, each a text"),
    ("status.json", "host", None, "status.json: key 'host' is None: expected a text"),
])
def test_a_status_field_not_as_nerfexp_writes_it_makes_the_run_damaged(tmp_path, file, key, value, says):
    run = make_run(tmp_path, "0", ["seed=0"], state="running")
    edit(run / file, **{key: value})
    read = read_run(run)
    assert read.state == "damaged" and read.detail.startswith(says), read.detail


@pytest.mark.parametrize(("line", "says"), [
    ({"step": "10", "wall_time_s": 1.0, "split": "val", "psnr": 20.0}, "line 1: key 'step' is '10'"),
    ({"step": 10, "wall_time_s": 1.0, "split": "val", "psnr": "20"}, "line 1: key 'psnr' is '20'"),
    ({"step": 10, "wall_time_s": math.inf, "split": "val", "psnr": 20.0}, "line 1: key 'wall_time_s' is inf"),
    ({"step": 10, "wall_time_s": 1.0, "split": ["val"], "psnr": 20.0}, "line 1: key 'split' is ['val']"),
    ({"step": 10, "wall_time_s": 1.0, "split": "val"}, "line 1: no key 'psnr'"),
    ([10, 1.0, "val", 20.0], "line 1: not a mapping of keys"),
    ({"step": 10, "wall_time_s": 1.0, "split": "val", "psnr": -math.inf}, "line 1: key 'psnr' is -inf"),
])
def test_a_metrics_line_not_as_nerfexp_writes_it_makes_the_run_damaged(tmp_path, line, says):
    run = make_run(tmp_path, "0", ["seed=0"])
    (run / "metrics.jsonl").write_text(json.dumps(line) + "\n")
    read = read_run(run)
    assert read.state == "damaged" and read.detail.startswith(f"metrics.jsonl: {says}"), read.detail


SCORE_VALUES = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.none(), st.just(...),
                         st.sampled_from([0, 30, -1, 10 ** 400, 5e-324, PSNR_LIMIT, 2.0]))


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(key=st.sampled_from(["test_psnr", "test_ssim"]), value=SCORE_VALUES)
def test_a_run_is_ranked_only_by_a_finite_score_in_range(tmp_path, key, value):
    # by hand: a score is one where it is a finite number in its range (PSNR [0, 242.55...], SSIM [-1, 1]);
    # missing, null, NaN or a PSNR's infinity: not scored; any other value: not as nerfexp writes it, damaged
    low, high = (0, PSNR_LIMIT) if key == "test_psnr" else (-1, 1)
    with tempfile.TemporaryDirectory(dir=tmp_path) as folder:
        run = make_run(Path(folder), "0", ["seed=0"])
        edit(run / "results.json", **{key: value})
        read = read_run(run)
    not_a_score = [math.inf] if key == "test_psnr" else []  # an image rendered exactly: PSNR's infinity
    if value is ... or value is None or (isinstance(value, float) and (math.isnan(value) or value in not_a_score)):
        shown = "missing" if value is ... else value
        assert (read.state, read.detail) == ("not scored", f"results.json: {key} is {shown}: no test score to rank by")
    elif low <= value <= high:
        assert read.state == "finished" and read.results[key] == value
    else:
        assert read.state == "damaged" and read.detail.startswith(f"results.json: key '{key}' is ")


def test_every_field_a_reader_uses_has_a_rule():
    # what the report, the page's pictures and nerfexp-eval read of results.json (src/nerfexp/report, find_run)
    read = {"test_psnr", "test_ssim", "test_lpips", "test_psnr_right_half", "test_ssim_right_half", "test_views",
            "test_psnr_per_view", "test_ssim_per_view", "test_lpips_per_view", "test_protocol", "test_cameras",
            "test_lpips_custom", "test_lpips_custom_per_view", "lpips_weights_sha256", "collapse", "choices", "overrides", "precision", "config.seed", "config.trainer.precision",
            "machine", "train_time_s", "time_per_step_s", "rays_per_s", "n_params", "other_load",
            "evaluations_per_ray", "checkpoint.path", "checkpoint.sha256", "steps", "test_budgets",
            "budget_scoring_s", "test_resolution", "split", "scene.name", "scene.catalog", "scene.sha256"}
    assert read == set(RESULTS_FIELDS)


def read_csv(path: Path) -> dict[str, dict]:
    with open(path) as file:
        return {row["variant"]: row for row in csv.DictReader(file)}


def test_the_report_ranks_only_scored_runs_and_lists_the_rest(tmp_path):
    # a: seeds 0, 1 at 20 and 22 dB, scored; b: seed 0 at 30 dB, seed 1 whose score is NaN; c: collapsed, with
    # a score that would rank it first; d: test_cameras null; e: a right half as text; f: only a NaN score
    for seed, psnr in enumerate((20.0, 22.0)):
        make_run(tmp_path, f"a{seed}", ["encoding=a", f"seed={seed}"], psnr=psnr)
    make_run(tmp_path, "b0", ["encoding=b", "seed=0"], psnr=30.0)
    edit(make_run(tmp_path, "b1", ["encoding=b", "seed=1"]) / "results.json", test_psnr=math.nan)
    collapse = "step 40: the fine network rendered nothing (opacity below 0.0001 on every ray) for 200 batches"
    edit(make_run(tmp_path, "c0", ["encoding=c", "seed=0"], psnr=40.0) / "results.json", collapse=collapse)
    edit(make_run(tmp_path, "d0", ["encoding=d", "seed=0"], psnr=41.0) / "results.json", test_cameras=None)
    edit(make_run(tmp_path, "e0", ["encoding=e", "seed=0"], psnr=42.0) / "results.json",
         test_psnr_right_half="31.2")
    edit(make_run(tmp_path, "f0", ["encoding=f", "seed=0"]) / "results.json", test_psnr=math.inf)
    write_report([tmp_path], tmp_path, reference="encoding=a")
    report = (tmp_path / "report.md").read_text()
    assert "Runs: 8 (3 finished, 1 collapsed, 2 not scored, 2 damaged)" in report
    ranking = report[report.index("## Ranking"):report.index("## Jobs")]
    # b's one scored seed against a's seed 0: 30 - 20, one pair, no interval: one line
    assert "1. encoding=b (30.00 dB), encoding=a (21.00 dB)" in ranking
    assert all(f"encoding={v}" not in ranking for v in "cdef")
    assert f"- `{tmp_path / 'c0'}` (encoding=c, seed=0): collapsed: {collapse}" in report
    assert (f"- `{tmp_path / 'b1'}` (encoding=b, seed=1): not scored: results.json: test_psnr is nan: no test score "
            "to rank by") in report
    assert f"- `{tmp_path / 'f0'}` (encoding=f, seed=0): not scored: results.json: test_psnr is inf" in report
    assert (f"- `{tmp_path / 'd0'}` (encoding=d, seed=0): damaged: results.json: key 'test_cameras' is None: "
            "expected one of given, refined") in report
    assert (f"- `{tmp_path / 'e0'}` (encoding=e, seed=0): damaged: results.json: key 'test_psnr_right_half' is "
            "'31.2'") in report
    rows = read_csv(tmp_path / "report.csv")
    assert (rows["encoding=b"]["finished"], float(rows["encoding=b"]["test_psnr_mean"])) == ("1", 30.0)
    assert float(rows["encoding=b"]["psnr_diff"]) == 10.0 and rows["encoding=b"]["paired_seeds"] == "1"
    for unscored in "cdef":  # in the table, counted as runs, with no mean and no difference
        row = rows[f"encoding={unscored}"]
        assert (row["runs"], row["finished"]) == ("1", "0") and math.isnan(float(row["test_psnr_mean"]))
        assert row["paired_seeds"] == "" or row["paired_seeds"] == "0"


def test_nerfexp_eval_names_a_checkpoint_record_not_as_nerfexp_writes_it(tmp_path):
    run = make_run(tmp_path, "0", ["seed=0"])
    (run / ".hydra").mkdir()
    (run / ".hydra" / "config.yaml").write_text("seed: 0\n")
    (run / "checkpoints").mkdir()
    (run / "checkpoints" / "last.ckpt").write_bytes(b"weights")
    for checkpoint, says in [("last.ckpt", "key 'checkpoint' is 'last.ckpt': expected a mapping"),
                             ({"path": ["last.ckpt"], "sha256": "0" * 64}, "key 'checkpoint.path' is ['last.ckpt']"),
                             ({"path": "checkpoints/last.ckpt"}, "no key 'checkpoint.sha256'")]:
        edit(run / "results.json", checkpoint=checkpoint)
        with pytest.raises(NerfexpError) as caught:
            find_run(run)
        assert str(caught.value).startswith(f"{run / 'results.json'}: {says}") and "\n" not in str(caught.value)


def test_a_run_directory_whose_status_is_odd_is_described_and_never_replaced(tmp_path):
    run = make_run(tmp_path, "0", ["seed=0"], state="failed", error="NerfexpError: stopped")
    edit(run / "status.json", overrides=[1, 2])
    assert held_run(run) == ("a run whose status.json is not as nerfexp writes it (key 'overrides' is [1, 2]: "
                             "expected a list of items, each a text)")
    with pytest.raises(NerfexpError, match="holds a run whose status.json is not as nerfexp writes it"):
        admit_run(run, None)


@pytest.mark.parametrize(("c2w", "says"), [
    ("poses", "got a str"),
    ([], "got an empty list"),
    ([[[1, 0, 0, 10 ** 400], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]], "item 0 is not a 4 x 4 matrix of numbers"),
    ([[[1, 0, 0, 1e300], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]], "item 0 is not a rigid camera pose: its position"),
    ([[[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]], "item 0 is not a rigid camera pose"),
])
def test_refined_cameras_that_are_not_rigid_poses_are_one_line(tmp_path, c2w, says):
    (tmp_path / "cameras").mkdir()
    (tmp_path / "cameras" / "train_poses.json").write_text(json.dumps({"c2w": c2w}))
    with pytest.raises(NerfexpError) as caught:
        read_refined_poses(tmp_path)
    message = str(caught.value)
    assert message.startswith(f"{tmp_path / 'cameras' / 'train_poses.json'}: not a record of refined cameras")
    assert says in message and "\n" not in message, message


def test_validation_curves_with_nan_and_infinite_psnr_are_plotted_and_the_scores_reported(tmp_path):
    # nerfexp writes a validation PSNR of NaN (a render that was not finite) or infinity (an image rendered
    # exactly): the curves hold them, and the report is written from the test scores as ever
    make_run(tmp_path, "a0", ["encoding=a", "seed=0"], curve=((50.0, math.nan), (100.0, math.inf)))
    make_run(tmp_path, "a1", ["encoding=a", "seed=1"], psnr=22.0, curve=((50.0, 15.0), (100.0, 18.0)))
    write_report([tmp_path], tmp_path)
    assert "| encoding=a | 2/2 | 21.00 ± 1.41 |" in (tmp_path / "report.md").read_text()
    assert (tmp_path / "psnr_vs_time.png").stat().st_size > 0


EXTREMES = [math.nan, math.inf, -math.inf, 5e-324, 1e300, 10 ** 400, -1, True, None, "", "x\ny", [], {}, [1.0],
            {"x": 1}]
ANY_VALUE = st.one_of(st.sampled_from(EXTREMES), st.floats(allow_nan=True, allow_infinity=True), st.integers(),
                      st.text(max_size=4), st.lists(st.integers(), max_size=3))


def run_with(root: Path, name: str, key: str, value) -> Path:
    """A finished run (``make_run``, seed 0) whose results.json holds ``value`` at ``key`` (dots: in mappings)."""
    run = make_run(root, name, [f"seed={name}"])
    results = json.loads((run / "results.json").read_text())
    *parents, last = key.split(".")
    inner = results
    for part in parents:
        inner = inner.setdefault(part, {})
    inner[last] = value
    (run / "results.json").write_text(json.dumps(results))
    return run


def read_as_expected(read, key: str) -> bool:
    """Whether a run with an odd value at ``key`` was read as the report reads any run: scored, not scored,
    collapsed, or damaged naming the key (or the mapping on its way: first, or, where the value breaks a relation
    to another key, nerfexp.rundir.records.relations_problem, beside it), on one line."""
    named = f"key '{key.split('.')[0]}"
    return (read.state in ("finished", "not scored", "collapsed", "damaged") and "\n" not in read.detail
            and (read.state != "damaged" or (read.detail.startswith("results.json: key '") and named in read.detail)))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(key=st.sampled_from(sorted(RESULTS_FIELDS)), value=ANY_VALUE)
def test_a_run_with_any_value_in_any_field_is_read(tmp_path, key, value):
    with tempfile.TemporaryDirectory(dir=tmp_path) as folder:
        read = read_run(run_with(Path(folder), "0", key, value))
    assert read_as_expected(read, key), (read.state, read.detail)


def test_a_report_over_runs_with_every_odd_value_in_every_field_is_written(tmp_path):
    # one variant (the runs differ in their seeds alone), a run per field and odd value: the report is written,
    # and its mean is over the runs that kept a score
    odd = [(key, value) for key in sorted(RESULTS_FIELDS) for value in EXTREMES]
    runs = [run_with(tmp_path, str(i), key, value) for i, (key, value) in enumerate(odd)]
    write_report([tmp_path], tmp_path)
    reads = [read_run(run) for run in runs]
    assert all(read_as_expected(read, key) for read, (key, _) in zip(reads, odd))
    scored = [read for read in reads if read.state == "finished"]
    row = read_csv(tmp_path / "report.csv")["default"]
    assert (int(row["runs"]), int(row["finished"])) == (len(odd), len(scored)) and 0 < len(scored) < len(odd)
    # 20 dB each, as make_run wrote them, but the run whose test_psnr is 5e-324 (a PSNR in range): 20 (n - 1) / n
    assert math.isclose(float(row["test_psnr_mean"]), 20.0 * (len(scored) - 1) / len(scored))
    assert [read.results["test_psnr"] for read in scored].count(5e-324) == 1
