"""Data-parallel training (``trainer=ddp``) on two CPU processes over gloo: each process trains on its own
part of every global batch, evaluation is shared out and gathered, and one process writes the run."""

import json
from pathlib import Path

import pytest
import torch
from hydra.utils import instantiate

from nerfexp.data.rays import RandomRays, rank_slice
from nerfexp.data.views import Views
from nerfexp.errors import ConfigError
from nerfexp.geometry.lenses import Intrinsics
from nerfexp.products.trained import load_module
from nerfexp.rundir.layout import LAST_CHECKPOINT
from nerfexp.rundir.trained import run_config
from nerfexp.scoring.metrics import psnr, ssim
from tests.helpers import TINY, read_json, run_nerfexp

DDP = ["trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=2"]
RAYS = ("origins", "directions", "rgb")


def views(n=4, h=16, w=16) -> Views:
    c2w = torch.eye(4).repeat(n, 1, 1)
    c2w[:, :3, 3] = torch.arange(n, dtype=torch.float32)[:, None]  # a camera per view, told apart by origin
    return Views(rgba=torch.rand(n, h, w, 4, generator=torch.Generator().manual_seed(0)), c2w=c2w,
                 intrinsics=Intrinsics.pinhole(12.0, h, w, (n,)))


@pytest.mark.parametrize("world_size", [2, 4])
def test_the_ranks_share_out_the_batch_one_process_draws(world_size):
    scene, background = views(), torch.ones(3)
    alone = iter(RandomRays(scene, background, batch_rays=64, seed=3))
    ranks = [iter(RandomRays(scene, background, batch_rays=64, seed=3, rank=r, world_size=world_size))
             for r in range(world_size)]
    for _ in range(3):  # batches 0, 1, 2
        whole, parts = next(alone), [next(rank) for rank in ranks]
        assert all(len(part["rgb"]) == 64 // world_size for part in parts)
        # the parts laid end to end are the one-process batch: every ray once, none on two ranks
        for key in RAYS:
            assert torch.equal(torch.cat([part[key] for part in parts]), whole[key]), key
        # each rank jitters its rays from its own seed; rank 0's is the one-process seed
        assert parts[0]["seed"] == whole["seed"] and len({part["seed"] for part in parts}) == world_size


def test_ranks_hold_disjoint_rays_of_the_same_batch():
    # Two ranks' rays, as (view, ray direction) pairs: the pixels rank 0 trains on are not those of rank 1
    # (the image is large enough that 32 random draws repeat no pixel with this seed; a repeat within one
    # process's batch would be sampling with replacement, not duplication across ranks).
    scene = views(n=2, h=64, w=64)
    parts = [next(iter(RandomRays(scene, torch.ones(3), batch_rays=32, seed=0, rank=r, world_size=2)))
             for r in (0, 1)]
    rays = [{tuple(torch.cat([o, d]).tolist()) for o, d in zip(p["origins"], p["directions"])} for p in parts]
    assert len(rays[0]) == len(rays[1]) == 16 and not rays[0] & rays[1]


def test_a_batch_that_does_not_divide_among_the_processes_is_refused():
    assert rank_slice(1024, 3, 4) == slice(768, 1024)
    with pytest.raises(ConfigError, match=r"scale.batch_rays=100 .* multiple of 3"):
        RandomRays(views(), torch.ones(3), batch_rays=100, seed=0, rank=0, world_size=3)


def test_a_batch_that_does_not_divide_is_one_line_before_any_process_starts(tmp_path):
    done = run_nerfexp(*DDP[:2], "trainer.devices=3", "scale.batch_rays=256", f"hydra.run.dir={tmp_path}",
                       new_process=True, cwd=tmp_path)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1 and "Traceback" not in done.stderr
    assert lines[-1] == ("nerfexp: error: scale.batch_rays=256 is the global batch, split evenly over 3 processes "
                         "(trainer.devices x trainer.num_nodes): choose a multiple of 3")
    assert read_json(tmp_path / "status.json")["state"] == "failed"


def single_process_scores(run_dir: Path) -> list[tuple[float, float]]:
    """PSNR and SSIM of each test view rendered by the run's last checkpoint in this process, without
    Lightning: the truth that the distributed evaluations must reproduce."""
    cfg = run_config(run_dir)
    module, _ = load_module(cfg, run_dir / LAST_CHECKPOINT)
    datamodule = instantiate(cfg.datamodule)
    scores = []
    precision = read_json(run_dir / "results.json")["precision"]  # the config holds the choice: auto
    bf16 = torch.autocast("cpu", dtype=torch.bfloat16, enabled=precision == "bf16-mixed")
    for batch in datamodule.test_dataloader():
        with bf16:  # as the run's trainer evaluates
            image = module.render_image(batch["origins"], batch["directions"], batch.get("viewdirs"))
        scores.append((psnr(image["rgb"], batch["rgb"]), ssim(image["rgb"], batch["rgb"])))
    return scores


@pytest.fixture(scope="module")
def ddp_sweep(tmp_path_factory) -> Path:
    """A multirun of two jobs (seeds 0 and 1), each trained by two CPU processes (gloo) for 20 steps, run
    once for the tests below; the sweep directory is ``ROOT/sweep``, run from ``ROOT``. 3 test views on
    2 processes: Lightning's sampler repeats one view to even them out.

    Lightning's plain ``ddp`` would re-run the command line, -m and all, in its second process: the
    sweep again, into other directories, and a second job that hangs. ``trainer=ddp`` spawns instead."""
    root = tmp_path_factory.mktemp("ddp")
    done = run_nerfexp("-m", *TINY, *DDP, "scale.steps=20", "scale.val_every=10", "data.n_test=3", "seed=0,1",
                       f"hydra.sweep.dir={root / 'sweep'}", new_process=True, cwd=root)
    assert done.returncode == 0, done.stderr[-3000:]
    return root / "sweep"


@pytest.mark.slow
def test_a_multirun_of_ddp_jobs_runs_each_job_once(ddp_sweep):
    assert sorted(p.name for p in ddp_sweep.parent.iterdir()) == ["sweep"]  # no outputs/, multirun/, lightning_logs/
    assert sorted(p.name for p in ddp_sweep.iterdir()) == ["0", "1", "multirun.yaml"]
    assert sorted(p.relative_to(ddp_sweep).as_posix() for p in ddp_sweep.rglob("results.json")) == [
        "0/results.json", "1/results.json"]
    for job in (0, 1):
        results = read_json(ddp_sweep / str(job) / "results.json")
        assert (results["processes"], results["steps"], results["choices"]["seed"]) == (2, 20, job)
        assert read_json(ddp_sweep / str(job) / "status.json")["state"] == "finished"


@pytest.mark.slow
def test_two_cpu_processes_train_and_record_once(ddp_sweep):
    run_dir = ddp_sweep / "0"
    results = read_json(run_dir / "results.json")
    assert (results["processes"], results["steps"], results["batch_rays"]) == (2, 20, 256)
    assert results["cpu_time_s"] > 0  # both processes' (summed over the ranks as training ends)
    assert sorted(p.name for p in (run_dir / "test").iterdir()) == sorted(
        f"r_{i}{suffix}.png" for i in range(3) for suffix in ("", "_depth", "_error", "_target"))
    # each evaluation recorded once, by rank 0, with the step of the weights it scored
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    # the test views scored at the default budgets (a quarter and a half: steps 5 and 10) by every process, once
    assert [(r["split"], r["step"]) for r in records] == [("test", 5), ("test", 10), ("val", 10), ("val", 20),
                                                          ("test", 20)]
    assert results["val_psnr"] == records[3]["psnr"] and results["test_psnr"] == records[4]["psnr"]
    assert [(b["step"], b["test_psnr"]) for b in results["test_budgets"]] == [
        (r["step"], r["psnr"]) for r in records if r["split"] == "test"]


@pytest.mark.slow
def test_distributed_evaluation_of_a_checkpoint_scores_as_one_process(ddp_sweep, tmp_path):
    run_dir = ddp_sweep / "0"
    truth = single_process_scores(run_dir)
    # The run's final test is a distributed evaluation of a fixed checkpoint (the last): its means over
    # the 3 views are those of one process scoring each view once.
    results = read_json(run_dir / "results.json")
    assert results["test_psnr"] == pytest.approx(sum(p for p, _ in truth) / 3, abs=1e-6)
    assert results["test_ssim"] == pytest.approx(sum(s for _, s in truth) / 3, abs=1e-6)

    # nerfexp-eval on the run's trainer (2 processes) scores every view once, as one process does
    scored = run_nerfexp(str(run_dir), new_process=True, cwd=tmp_path, script="nerfexp-eval")
    assert scored.returncode == 0, scored.stderr[-3000:]
    evaluation = read_json(run_dir / "eval.json")
    assert evaluation["processes"] == 2 and evaluation["step"] == 20
    assert evaluation["test_views"] == results["test_views"] == [0, 1, 2]
    assert evaluation["test_psnr_per_view"] == pytest.approx([p for p, _ in truth], abs=1e-6)
    assert evaluation["test_ssim_per_view"] == pytest.approx([s for _, s in truth], abs=1e-6)
    assert results["test_psnr_per_view"] == pytest.approx([p for p, _ in truth], abs=1e-6)
    assert (evaluation["test_psnr"], evaluation["test_ssim"]) == (results["test_psnr"], results["test_ssim"])


@pytest.mark.slow
def test_hash_tables_train_with_dense_gradients_under_ddp(tmp_path):
    # DDP all-reduces dense gradients (a sparse one stops its reducer: "Cannot access storage of
    # SparseTensorImpl"): with several processes the module makes the tables' gradients dense, once, and says so
    # field=nerf: the tiny run's scale.depth, width and skips, which hashgrid's own field=ngp would leave unused
    done = run_nerfexp(*TINY, *DDP, "encoding=hashgrid", "field=nerf", "encoding.position.sparse_gradients=true",
                       "model.optimizer._target_=nerfexp.training.optimizers.LazyAdam",
                       "encoding.position.log2_table_size=12", "encoding.position.finest=64", "scale.steps=10", "scale.val_every=10",
                       f"hydra.run.dir={tmp_path}", new_process=True, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    results = read_json(tmp_path / "results.json")
    assert (results["processes"], results["steps"]) == (2, 10)
    assert results["config"]["encoding"]["position"]["sparse_gradients"] is True
    # said once, by the first process (a spawned one: its warnings reach standard error)
    lines = [line for line in done.stderr.splitlines() if "gradients are dense" in line]
    assert len(lines) == 1 and lines[0].endswith("2 processes: the hash tables' gradients are dense (DDP all-reduces "
                                                 "dense gradients); encoding.position.sparse_gradients=true applies "
                                                 "to one process")


@pytest.mark.slow
def test_a_fog_under_ddp_is_judged_on_every_view_once_and_said_once(tmp_path):
    # 3 validation views on 2 processes: each process renders 2 (the sampler repeats one); the guard gathers them
    fog = ["model.renderer.field.density_bias=-8", "callbacks.guard.collapse_patience=10",
           "callbacks.guard.on_collapse=warn"]
    done = run_nerfexp(*TINY, *DDP, *fog, "data.n_val=3", "data.n_test=3", f"hydra.run.dir={tmp_path}",
                       new_process=True, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    output = done.stdout + done.stderr
    assert output.count("step 30: every validation view rendered nothing (3 views: ") == 1
    assert read_json(tmp_path / "results.json")["collapse"].startswith("every test view rendered nothing (3 views: ")
