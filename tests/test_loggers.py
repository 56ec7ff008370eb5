"""Each logger of ``conf/logger/`` through a whole run: the run's validation scores, hyper-parameters and
images reach it, read back with the logger's own format or client."""

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from tests.helpers import TINY, run_nerfexp

LOGGED = [*TINY, "scale.steps=40", "scale.val_every=30"]  # validations at steps 30 and 40


def train_with(logger: str, run_dir: Path, *overrides: str) -> list[tuple[int, float]]:
    """Run the LOGGED config with ``logger`` (and ``overrides``); its validations (step, PSNR) as metrics.jsonl
    has them."""
    result = run_nerfexp(*LOGGED, f"logger={logger}", *overrides, f"hydra.run.dir={run_dir}", cwd=run_dir)
    assert result.returncode == 0, result.stderr[-3000:]
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    validations = [(r["step"], r["psnr"]) for r in records if r["split"] == "val"]
    assert [step for step, _ in validations] == [30, 40]
    return validations


def pixels(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path))


def logged_test_image(run_dir: Path) -> np.ndarray:
    """What the loggers receive for test view 0: render, ground truth and depth side by side, built here
    from the files the run saved in test/."""
    view = {suffix: pixels(run_dir / "test" / f"r_0{suffix}.png") for suffix in ("", "_target", "_depth")}
    return np.concatenate([view[""], view["_target"], np.repeat(view["_depth"][..., None], 3, axis=2)], axis=1)


@pytest.mark.slow
def test_csv_logger_holds_the_scores_hyperparameters_and_images(tmp_path):
    validations = train_with("csv", tmp_path)
    with open(tmp_path / "csv" / "metrics.csv", newline="") as file:
        rows = list(csv.DictReader(file))
    assert [(int(r["step"]), float(r["val/psnr"])) for r in rows if r["val/psnr"]] == validations
    hparams = yaml.safe_load((tmp_path / "csv" / "hparams.yaml").read_text())
    assert hparams["encoding"] == "posenc" and hparams["logger"] == "csv" and hparams["scale.steps"] == "40"
    image = pixels(tmp_path / "csv" / "images" / "test" / "render_target_depth" / "0" / "step_0000040.png")
    assert np.array_equal(image, logged_test_image(tmp_path))
    assert sorted(p.name for p in (tmp_path / "csv" / "images" / "val" / "render_target_depth" / "0").iterdir()) == [
        "step_0000030.png", "step_0000040.png"]


@pytest.mark.slow
def test_mlflow_logger_holds_the_scores_hyperparameters_and_images(tmp_path):
    from mlflow import MlflowClient

    validations = train_with("mlflow", tmp_path, "tags=[baseline,lego]", "notes=first try")
    client = MlflowClient(tracking_uri=f"sqlite:///{tmp_path}/mlflow.db")
    (run,) = client.search_runs([client.get_experiment_by_name("nerfexp").experiment_id])
    assert run.info.status == "FINISHED"
    history = client.get_metric_history(run.info.run_id, "val/psnr")
    assert sorted((m.step, m.value) for m in history) == validations
    assert run.data.params["encoding"] == "posenc" and run.data.params["scale.steps"] == "40"
    # the labels as run tags (the notes: MLflow's run description), whole, as the parameters may not be
    assert json.loads(run.data.tags["tags"]) == ["baseline", "lego"]
    assert run.data.tags["mlflow.note.content"] == "first try"
    images = [a.path for a in client.list_artifacts(run.info.run_id, "images")]
    test_view_0 = "images/test~render_target_depth~0+step+40+"  # MLflow's name for the key at a step
    (test_image,) = [p for p in images if p.startswith(test_view_0) and p.endswith(".png")]
    downloaded = client.download_artifacts(run.info.run_id, test_image, str(tmp_path / "downloaded"))
    assert np.array_equal(pixels(Path(downloaded)), logged_test_image(tmp_path))


@pytest.mark.slow
def test_wandb_logger_offline_holds_the_run_and_its_images(tmp_path):
    train_with("wandb", tmp_path, "tags=[baseline,lego]", "notes=first try")
    (offline,) = (tmp_path / "wandb").glob("offline-run-*")  # offline: kept here for `wandb sync`
    record = next(offline.glob("run-*.wandb")).read_bytes()
    assert b"val/psnr" in record and b"posenc" in record  # the scores' key and a hyper-parameter's value
    # the run's tags and notes, each a text of the run's record (its length before it), beside the config's JSON
    assert b"\x04lego" in record and b"\x09first try" in record and b'"first try"' in record
    # test view 0 (W&B adds its own step and a hash to the name)
    (image,) = (offline / "files" / "media" / "images" / "test" / "render_target_depth").glob("0_*.png")
    assert np.array_equal(pixels(image), logged_test_image(tmp_path))
    log = (tmp_path / "wandb" / "debug.log").read_text()
    assert "finishing run" in log and "ERROR" not in log  # finished before the process exited


@pytest.mark.slow
def test_without_a_logger_the_run_writes_its_own_records(tmp_path):
    train_with("none", tmp_path)
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["choices"]["logger"] == "none" and results["val_psnr"] is not None
    assert not any((tmp_path / name).exists() for name in ("tensorboard", "csv", "mlflow.db", "wandb"))


def test_a_logger_whose_package_is_missing_is_one_line_before_any_work(tmp_path):
    result = run_nerfexp("logger._target_=lightning.pytorch.loggers.CometLogger", f"hydra.run.dir={tmp_path}",
                         cwd=tmp_path)
    assert result.returncode == 1 and "Traceback" not in result.stderr
    (line,) = [line for line in result.stderr.splitlines() if line.startswith("nerfexp: error:")]
    assert "logger._target_=lightning.pytorch.loggers.CometLogger needs a package that is not installed" in line
    assert not (tmp_path / "metrics.jsonl").exists()
