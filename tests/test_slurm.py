"""Sweeps through Hydra's submitit launcher onto a real SLURM scheduler (tests/slurm_cluster.py: slurmctld,
slurmd and munged on this machine): jobs of several DDP processes started by srun, a job array throttled by
``array_parallelism``, a failing job among others, and a job ended by its time limit, then resumed."""

import re
import subprocess
import time

import pytest
import torch

from nerfexp.rundir.layout import read_metrics
from tests.helpers import TINY, command, read_json, run_nerfexp
from tests.slurm_cluster import local_cluster, missing

pytestmark = pytest.mark.slow

# hydra/launcher=slurm sized for the test cluster: CPU processes over gloo, one CPU per process, 1 GB per job
ON_SLURM = ["-m", "hydra/launcher=slurm", "trainer=slurm", "trainer.accelerator=cpu", "hydra.launcher.partition=debug",
            "hydra.launcher.cpus_per_task=1", "hydra.launcher.mem_gb=1", *TINY]


@pytest.fixture(scope="module")
def cluster(tmp_path_factory) -> dict:
    """The environment of a running local cluster (``SLURM_CONF``), for this module's tests."""
    if reason := missing():  # as the browser tests fail without chromium: CI installs both (.ci/run)
        pytest.fail(f"no local SLURM cluster: {reason}")
    with local_cluster(tmp_path_factory.mktemp("slurm")) as env, pytest.MonkeyPatch.context() as patch:
        patch.setenv("SLURM_CONF", env["SLURM_CONF"])  # the sweeps' submissions and their jobs' srun
        yield env


def running_jobs(env: dict) -> set[str]:
    """The ids of the jobs running now (array tasks one by one)."""
    listing = subprocess.run(["squeue", "-h", "-r", "-t", "R", "-o", "%i"], capture_output=True, text=True, env=env)
    return set(listing.stdout.split())


@pytest.fixture(scope="module")
def sweep(cluster, tmp_path_factory) -> dict:
    """A sweep of four jobs, each two DDP processes (srun's tasks), at most two jobs at once
    (``array_parallelism=2``); the two with ``NanTargets`` fail at their first step. The scheduler's
    running jobs are sampled while it runs. It is submitted from a shell that exports a MASTER_ADDR and
    MASTER_PORT that lead nowhere, which sbatch passes on: the launcher's setup unsets them."""
    root = tmp_path_factory.mktemp("slurm_sweep")
    argv, env = command("nerfexp", *ON_SLURM, "trainer.devices=2", "hydra.launcher.array_parallelism=2",
                        "+callbacks.extra._target_=lightning.Callback,tests.helpers.NanTargets", "seed=0,1",
                        f"hydra.sweep.dir={root / 'sweep'}")
    env.update(MASTER_ADDR="nowhere.invalid", MASTER_PORT="1")
    process = subprocess.Popen(argv, cwd=root, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    at_once, deadline = [], time.monotonic() + 600
    while process.poll() is None:
        if time.monotonic() > deadline:
            process.kill()
            pytest.fail(f"the sweep on SLURM did not end in 600 s; its jobs' logs: {root / 'sweep' / '.submitit'}")
        at_once.append(running_jobs(cluster))
        time.sleep(0.25)
    stdout, stderr = process.communicate()
    return {"dir": root / "sweep", "returncode": process.returncode, "stderr": stderr, "at_once": at_once}


def test_each_job_of_a_sweep_trains_as_ddp_processes_that_srun_started(sweep, tmp_path):
    sweep_dir = sweep["dir"]
    script = next(sweep_dir.glob(".submitit/*/*_submission.sh")).read_text()
    assert "#SBATCH --ntasks-per-node=2" in script and "--gpus" not in script  # gloo on the CPU: no GPUs asked
    assert "\nunset MASTER_ADDR MASTER_PORT\n" in script  # the submitting shell's, which lead nowhere here
    assert re.search(r"^srun .*submitit\.core\._submit", script, re.MULTILINE)
    for job, seed in ((0, 0), (1, 1)):  # lightning.Callback: the jobs that train
        results = read_json(sweep_dir / str(job) / "results.json")
        assert results["processes"] == 2 and results["steps"] == 60 and results["choices"]["seed"] == seed
        assert read_json(sweep_dir / str(job) / "status.json")["state"] == "finished"
    logs = sorted(sweep_dir.glob(".submitit/*_0/*_log.err"))  # array task 0: one log per srun task
    assert [log.name.rsplit("_", 2)[-2] for log in logs] == ["0", "1"]
    for rank, log in enumerate(logs):
        assert f"GLOBAL_RANK: {rank}, MEMBER: {rank + 1}/2" in log.read_text()
    report = run_nerfexp(str(sweep_dir), script="nerfexp-report", cwd=tmp_path)
    assert report.returncode == 0, report.stderr[-3000:]
    page = (sweep_dir / "report.md").read_text()
    assert "Runs: 4 (2 finished, 2 failed)" in page
    assert "| +callbacks.extra._target_=lightning.Callback | 2/2 |" in page


def test_the_array_runs_its_jobs_two_at_a_time_and_a_failing_job_stops_no_other(sweep):
    sweep_dir = sweep["dir"]
    script = next(sweep_dir.glob(".submitit/*/*_submission.sh")).read_text()
    assert "#SBATCH --array=0-3%2" in script
    most = max(len(jobs) for jobs in sweep["at_once"])
    assert most == 2, sweep["at_once"]  # the node fits four 2-task jobs (8 CPUs); SLURM ran two at once
    states = {job: read_json(sweep_dir / str(job) / "status.json") for job in range(4)}
    assert [states[job]["state"] for job in range(4)] == ["finished", "finished", "failed", "failed"]
    assert all(states[job]["error"].startswith("NonFiniteError: step 0") for job in (2, 3))
    # the sweep ends after every job, with one line naming the first failure, and exit status 1
    assert sweep["returncode"] == 1
    last = sweep["stderr"].strip().splitlines()[-1]
    assert last.startswith("nerfexp: error: step 0: the coarse network's colour loss is nan"), sweep["stderr"][-2000:]


def test_a_job_at_its_time_limit_records_sigterm_and_resume_continues_it(cluster, tmp_path):
    # a minute's limit (SLURM's least), its notice (submitit's USR2) 10 s before: SLURM sends both while it trains,
    # a step each 0.1 s (PacedSteps), which leaves the cores to the tests beside it for that minute and more
    first = run_nerfexp(*ON_SLURM, "trainer.devices=2", "scale.steps=1000000", "hydra.launcher.timeout_min=1",
                        "hydra.launcher.signal_delay_s=10", "+callbacks.paced._target_=tests.helpers.PacedSteps",
                        "+callbacks.paced.seconds=0.1", f"hydra.sweep.dir={tmp_path / 'first'}", cwd=tmp_path,
                        new_process=True)
    run_dir = tmp_path / "first" / "0"
    checkpoint = run_dir / "checkpoints" / "last.ckpt"
    assert first.returncode == 1, first.stderr[-3000:]
    assert first.stderr.strip().splitlines()[-1] == (
        f"nerfexp: error: {run_dir}: ended by SIGTERM (on SLURM: a time limit, scancel or preemption); "
        f"the job's overrides with resume={checkpoint} continue it")
    status = read_json(run_dir / "status.json")
    assert (status["state"], status["signal"], status["error"]) == ("failed", "SIGTERM", "ended by SIGTERM")
    task_logs = "".join(p.read_text() for p in (tmp_path / "first").glob(".submitit/*/*_log.*"))
    assert "DUE TO TIME LIMIT" in task_logs  # slurmstepd's own record of why it ended the job
    assert "SIGUSR2: SLURM's notice that the job nears its time limit" in (run_dir / "nerfexp.log").read_text()
    step = torch.load(checkpoint, map_location="cpu", weights_only=True)["global_step"]
    assert step > 0
    resumed = run_nerfexp(*ON_SLURM, "trainer.devices=2", f"scale.steps={step + 30}", f"resume={checkpoint}",
                          f"hydra.sweep.dir={tmp_path / 'resumed'}", new_process=True, cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    results = read_json(tmp_path / "resumed" / "0" / "results.json")
    assert results["steps"] == step + 30 and results["processes"] == 2
    assert [r["step"] for r in results["resumes"]] == [step]
    first_logged = read_metrics(tmp_path / "resumed" / "0", ended=True)[0]["step"]
    assert first_logged > step  # trained on from the checkpoint, not from the start
