"""The sweeps in sweeps/: what they compose into, and the smoke sweep end to end through the report."""

import csv
import itertools
import math
import re

import imageio.v3 as iio
import pytest
from hydra import compose, initialize_config_module
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.types import RunMode
from omegaconf import OmegaConf
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.plugins.hparams.plugin_data_pb2 import HParamsPluginData

from nerfexp.report.publications import BLENDER_PSNR
from nerfexp.settings.checks import check_settings
from tests.helpers import TINY, read_json, run_nerfexp

# The paper's Table 4, written out independently of conf/ablation/: position L (None: raw xyz),
# direction L (None: raw; the rows 7 and 8 values are ours, scaled in proportion), view dependence,
# hierarchical, number of training images (None: all of the scene's, the paper's 100 on its synthetic scenes).
TABLE_4 = {
    "no_pe_vd_h": (None, None, False, False, None),
    "no_posenc": (None, None, True, True, None),
    "no_view_dependence": (10, 4, False, True, None),
    "no_hierarchical": (10, 4, True, False, None),
    "far_fewer_images": (10, 4, True, True, 25),
    "fewer_images": (10, 4, True, True, 50),
    "fewer_frequencies": (5, 2, True, True, None),
    "more_frequencies": (15, 6, True, True, None),
    "complete": (10, 4, True, True, None),
}


def sweep_jobs(name: str, arguments: tuple[str, ...] = ()) -> list[list[str]]:
    """The override lists of a sweep's jobs as Hydra's basic sweeper expands them: the sweep's params, then
    the command line's ``arguments`` (a key given again takes the later values, in the first one's place),
    every combination of the keys' values, the first key varying slowest (Hydra's public override parser)."""
    with initialize_config_module("nerfexp.conf", version_base=None):
        cfg = compose("config", overrides=[f"+sweeps={name}"], return_hydra_config=True)
    assert cfg.hydra.mode == RunMode.MULTIRUN
    params = [f"{key}={value}" for key, value in cfg.hydra.sweeper.params.items()] + list(arguments)
    values = {}
    for override in OverridesParser.create().parse_overrides(params):
        key = override.get_key_element()
        swept = override.is_sweep_override()
        each = override.sweep_string_iterator() if swept else [override.get_value_element_as_str()]
        values[key] = [f"{key}={value}" for value in each]
    return [list(job) for job in itertools.product(*values.values())]


def encoding_l(node) -> int | None:
    return node.n_freqs if node._target_.endswith("PositionalEncoding") else None


@pytest.mark.parametrize("name, scale", [("paper_ablation", "paper"), ("cpu_ablation", "cpu")])
def test_ablation_sweeps_are_the_nine_rows_of_table_4(name, scale):
    root = ["data.root=/data/lego"] if name == "paper_ablation" else []
    jobs = sweep_jobs(name, tuple(root))
    assert len(jobs) == 27  # 9 rows x 3 seeds
    rows = {job[0].split("=")[1] for job in jobs}
    assert rows == set(TABLE_4) and sorted(job[1] for job in jobs[:3]) == ["seed=0", "seed=1", "seed=2"]
    for row, (l_x, l_d, view_dependent, hierarchical, n_images) in TABLE_4.items():
        with initialize_config_module("nerfexp.conf", version_base=None):
            cfg = compose("config", overrides=[f"+sweeps={name}", f"ablation={row}", *root])
        renderer = cfg.model.renderer
        assert (encoding_l(renderer.field.position_encoding), encoding_l(cfg.encoding.direction)) == (l_x, l_d), row
        assert renderer.field.view_head._target_.endswith("MLPViewDependence" if view_dependent
                                                          else "NoViewDependence"), row
        assert (renderer.sampler.hierarchical, cfg.data.n_train) == (hierarchical, n_images), row
        if l_x is not None:  # the paper's gamma(x); at 64 px the CPU rows encode x / 8 (sweeps/cpu_ablation.yaml)
            assert renderer.field.position_encoding.input_scale == (1.0 if scale == "paper" else 0.125), row
        if scale == "paper":  # (Nc, Nf) = (64, 128); without hierarchy one network with Nc = 256
            assert cfg.data._target_.endswith("BlenderScene") and cfg.data.root == "/data/lego"
            assert (renderer.sampler.n_coarse, renderer.sampler.n_fine, renderer.sampler.n_single) == (64, 128, 256)
            assert (cfg.scale.width, cfg.scale.depth, cfg.scale.batch_rays) == (256, 8, 4096)
        else:
            assert cfg.data._target_.endswith("ProceduralScene")


def test_the_paper_ablation_over_the_papers_8_blender_scenes_by_name():
    jobs = sweep_jobs("paper_ablation_blender")
    assert len(jobs) == 9 * 3 * 8  # rows x seeds x scenes
    scenes = {job[2].split("=")[1] for job in jobs}
    assert scenes == set(BLENDER_PSNR) == {f"blender/{name}" for name in
                                           ("chair", "drums", "ficus", "hotdog", "lego", "materials", "mic", "ship")}
    assert {job[0].split("=")[1] for job in jobs} == set(TABLE_4)
    for job in jobs[:8]:  # one row and seed on each scene: the paper's scale, the scene by name, no folder
        with initialize_config_module("nerfexp.conf", version_base=None):
            cfg = compose("config", overrides=["+sweeps=paper_ablation_blender", *job], return_hydra_config=True)
        check_settings(cfg)
        assert cfg.data._target_.endswith("BlenderScene") and cfg.data.root is None
        assert cfg.data.scene == job[2].split("=")[1] and cfg.trainer.max_steps == 200_000
        assert str(cfg.hydra.sweep.dir).startswith("multirun/paper_ablation_blender/")


def test_sparse_tables_sweep_pairs_dense_and_sparse_table_gradients_under_one_optimizer():
    jobs = sweep_jobs("sparse_tables")
    assert len(jobs) == 6 and {job[0] for job in jobs[:2]} == {"seed=0"}  # each seed's pair together
    configs = []
    for job in jobs[:2]:
        with initialize_config_module("nerfexp.conf", version_base=None):
            cfg = compose("config", overrides=["+sweeps=sparse_tables", *job])
        check_settings(cfg)  # LazyAdam takes sparse gradients: no refusal
        configs.append(cfg)
    dense, sparse = ({key: OmegaConf.to_container(cfg[key], resolve=True) for key in ("encoding", "model", "scale")}
                     for cfg in configs)
    assert [job[1].lower() for job in jobs[:2]] == ["encoding.position.sparse_gradients=false",
                                            "encoding.position.sparse_gradients=true"]
    for config, flag in ((dense, False), (sparse, True)):
        assert config["model"]["renderer"]["field"]["position_encoding"].pop("sparse_gradients") is flag
        # the proposal networks (built only with hierarchical=proposal) take the encoding axis's encoding too
        proposal = config["model"]["renderer"]["sampler"]["proposal"]
        assert proposal["network"]["position_encoding"].pop("sparse_gradients") is flag
        assert config["encoding"]["position"].pop("sparse_gradients") is flag
    assert dense == sparse  # nothing else differs
    assert dense["encoding"]["position"]["_target_"].endswith("HashGridEncoding")
    assert dense["model"]["optimizer"]["_target_"] == "nerfexp.training.optimizers.LazyAdam"
    assert dense["model"]["renderer"]["grid"]["_target_"].endswith("OccupancyGrid")


def test_successors_sweep_crosses_the_papers_sampling_and_view_head_with_their_successors():
    jobs = sweep_jobs("successors")
    assert len(jobs) == 12
    seen = set()
    for job in jobs:
        with initialize_config_module("nerfexp.conf", version_base=None):
            cfg = compose("config", overrides=["+sweeps=successors", *job])
        check_settings(cfg)
        renderer = cfg.model.renderer
        seen.add((renderer.sampler.hierarchical, renderer.field.view_head._target_.rsplit(".", 1)[1], cfg.seed))
        assert cfg.trainer.max_steps == 1000 and cfg.data._target_.endswith("ProceduralScene")
    assert seen == {(h, head, seed) for h in (True, "proposal")
                    for head in ("MLPViewDependence", "ReflectionViewDependence") for seed in (0, 1, 2)}


def test_real_sweep_crosses_what_real_photographs_need_on_the_users_capture():
    jobs = sweep_jobs("real", ("data.root=/data/capture",))
    assert len(jobs) == 24
    seen = set()
    for job in jobs:
        with initialize_config_module("nerfexp.conf", version_base=None):
            cfg = compose("config", overrides=["+sweeps=real", *job])
        check_settings(cfg)
        renderer = cfg.model.renderer
        seen.add((renderer.contraction is not None, renderer.appearance is not None,
                  cfg.model.camera_opt is not None, cfg.seed))
        assert cfg.trainer.max_steps == 2000 and cfg.data._target_.endswith("NerfstudioScene")
        assert cfg.data.root == "/data/capture"
        assert cfg.model.test_camera_fit is not None  # every variant's test cameras refined alike
    assert seen == set(itertools.product((False, True), (False, True), (False, True), (0, 1, 2)))


def test_appearance_sweep_pairs_no_embedding_with_the_embedding_on_images_of_varied_exposure():
    for changes in ("train", "all"):
        jobs = sweep_jobs("appearance", (f"data.appearance_changes={changes}",))
        assert len(jobs) == 6 and {job[0] for job in jobs[:2]} == {"seed=0"}  # each seed's pair together
        seen = set()
        for job in jobs:
            with initialize_config_module("nerfexp.conf", version_base=None):
                cfg = compose("config", overrides=["+sweeps=appearance", *job])
            check_settings(cfg)
            seen.add((cfg.model.renderer.appearance is not None, cfg.seed))
            assert cfg.data._target_.endswith("ProceduralScene") and cfg.data.appearance_changes == changes
            assert (cfg.data.image_size, cfg.data.n_train, cfg.trainer.max_steps) == (32, 40, 500)
        assert seen == set(itertools.product((False, True), (0, 1, 2)))


def test_command_line_overrides_beat_the_sweeps_own_values():
    jobs = sweep_jobs("smoke", ("seed=5",))
    assert sorted(" ".join(job) for job in jobs) == ["ablation=complete seed=5", "ablation=no_pe_vd_h seed=5"]
    assert len(sweep_jobs("smoke", ("seed=7,8,9",))) == 6


@pytest.mark.slow
def test_smoke_sweep_through_the_report(tmp_path):
    sweep = tmp_path / "smoke"
    done = run_nerfexp("+sweeps=smoke", f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    assert re.findall(r"\] - (job \d of \d): ", done.stdout) == [f"job {k} of 4" for k in (1, 2, 3, 4)]
    report = run_nerfexp(str(sweep), cwd=tmp_path, script="nerfexp-report", new_process=True)
    assert report.returncode == 0, report.stderr[-3000:]
    with open(sweep / "report.csv") as file:
        rows = list(csv.DictReader(file))
    assert sorted(row["variant"] for row in rows) == ["ablation=complete", "ablation=no_pe_vd_h"]
    for row in rows:
        assert (row["runs"], row["finished"]) == ("2", "2")
        for key in ("test_psnr_mean", "test_psnr_std", "test_ssim_mean", "train_time_s", "rays_per_s",
                    "n_params", "evaluations_per_ray"):
            assert math.isfinite(float(row[key])), (row["variant"], key)
        assert math.isnan(float(row["published_psnr"]))  # the built-in scene is no publication's
    for name in ("psnr_vs_time.png", "pareto.png"):
        assert iio.imread(sweep / name).shape[:2] == (500, 800)
    assert "## Ranking by mean test PSNR" in (sweep / "report.md").read_text()
    # the page: per test view the truth and each variant's render and error, every one a real run's picture
    html = (sweep / "report.html").read_text()
    pictures = re.findall(r'<img src="(report_images/[^"]+)"', html)
    views = re.findall(r"<h3>Test view (\d+)</h3>", html)
    assert views and len(pictures) == 5 * len(views) and 'class="missing"' not in html
    assert all(iio.imread(sweep / picture).ndim == 3 for picture in pictures)
    # TensorBoard's HPARAMS view: each job's choices and overrides, with the PSNR/SSIM scalars as metrics
    events = EventAccumulator(str(sweep / "0" / "tensorboard"))
    events.Reload()
    content = events.PluginTagToContent("hparams")["_hparams_/session_start_info"]
    hparams = HParamsPluginData.FromString(content).session_start_info.hparams
    assert hparams["ablation"].string_value == "complete" and hparams["seed"].number_value == 0
    assert hparams["hierarchical"].number_value == 1  # TensorBoard stores booleans as numbers
    assert {"val/psnr", "test/psnr", "test/ssim"} <= set(events.Tags()["scalars"])


@pytest.mark.slow
def test_the_readmes_sweep_runs_on_a_capture_in_nerfstudios_format_and_reports(tmp_path):
    # the README's command on a scene with a real lens and masked occluders (nerfexp-scene writes it), tiny
    scene = tmp_path / "capture"
    written = run_nerfexp(str(scene), "--format", "nerfstudio", "--lens", "real", "--occluders", "--resolution", "24",
                          "--n-train", "12", "--n-val", "1", "--n-test", "2", cwd=tmp_path, script="nerfexp-scene")
    assert written.returncode == 0, written.stderr[-3000:]
    tiny = [o for o in TINY if not o.startswith(("data.n_test", "scale.image_size"))]  # the built-in scene's keys
    sweep = tmp_path / "sweep"
    done = run_nerfexp("-m", "encoding=none,posenc", "hierarchical=true,false", "data=nerfstudio",
                       f"data.root={scene}", "data.near=2", "data.far=6", *tiny, "scale.n_single=48",
                       f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    results = [read_json(sweep / str(k) / "results.json") for k in range(4)]
    assert all(r["split"].startswith("the file's train_filenames") and len(r["test_views"]) == 2 for r in results)
    report = run_nerfexp(str(sweep), cwd=tmp_path, script="nerfexp-report")
    assert report.returncode == 0, report.stderr[-3000:]
    with open(sweep / "report.csv") as file:
        rows = list(csv.DictReader(file))
    assert len(rows) == 4 and all(math.isfinite(float(row["test_psnr_mean"])) for row in rows)


@pytest.mark.slow
def test_a_failing_job_does_not_stop_the_sweep_and_is_reported(tmp_path):
    sweep = tmp_path / "sweep"
    done = run_nerfexp("-m", *TINY, "scale.lr=-1,5e-3", f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert done.returncode != 0
    assert "scale.lr=-1 (which sets model.optimizer.lr): expected a finite number" in done.stderr
    assert read_json(sweep / "0" / "status.json")["state"] == "failed"
    assert read_json(sweep / "1" / "status.json")["state"] == "finished" and (sweep / "1" / "results.json").exists()
    report = run_nerfexp(str(sweep), cwd=tmp_path, script="nerfexp-report")
    assert report.returncode == 0, report.stderr
    text = (sweep / "report.md").read_text()
    assert "Runs: 2 (1 finished, 1 failed)" in text
    assert "failed: ConfigError: scale.lr=-1 (which sets model.optimizer.lr): expected a finite number > 0" in text


@pytest.mark.slow
def test_optuna_search_maximizes_validation_psnr(tmp_path):
    sweep = tmp_path / "optuna"
    done = run_nerfexp("+sweeps=optuna", *TINY, "hydra.sweeper.n_trials=2", f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    best = (sweep / "optimization_results.yaml").read_text()
    trials = [read_json(sweep / str(i) / "results.json") for i in range(2)]
    assert all(math.isfinite(t["val_psnr"]) for t in trials)
    best_value = max(t["val_psnr"] for t in trials)
    assert f"best_value: {best_value}" in best, best
    assert {k for o in trials[0]["overrides"] for k in [o.split("=")[0]]} >= {"scale.lr", "scale.batch_rays"}
