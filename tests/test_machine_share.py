"""The machine a run shares: CPU counters read from /proc/stat texts written by hand, the others' load from known
counter values, and the thread count from the CPUs and the jobs at once, and while training from samples of known
counters (``ThreadsFollowLoad``)."""

import logging
from types import SimpleNamespace

import pytest
import torch

from nerfexp import machine_share
from nerfexp.domains import THREAD_LIMIT
from nerfexp.machine_share import (
    BUSY_LOAD,
    Sample,
    busy_line,
    busy_ticks,
    follow_load,
    intra_op_threads,
    other_load,
    others_cpu_s,
    parallel_jobs,
    read_busy_s,
    requested_threads,
    share_record,
    start_threads,
)
from nerfexp.training import callbacks
from nerfexp.training.callbacks import ThreadsFollowLoad

# user nice system idle iowait irq softirq steal guest guest_nice
STAT = """cpu  100 100 100 100 100 100 100 100 100 100
cpu0 10 1 5 100 7 2 3 4 50 60
cpu1 20 0 10 300 0 0 0 0 0 0
cpu2 1 1 1 1 1 1 1 1 1 1
intr 123 4 5
ctxt 999
"""
# busy = user + nice + system + irq + softirq + steal (idle and iowait left out; guest counted in user already):
# cpu0 10+1+5+2+3+4 = 25, cpu1 20+0+10 = 30, cpu2 1+1+1+1+1+1 = 6
JOBLIB = "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher"


@pytest.mark.parametrize(("cpus", "expected"), [(None, 61), ({0}, 25), ({1}, 30), ({0, 2}, 31), ({2, 7}, 6)])
def test_busy_ticks_sum_the_allowed_cpus_lines_but_idle_iowait_and_guest(cpus, expected):
    assert busy_ticks(STAT, cpus) == expected


def test_a_text_without_the_allowed_cpus_lines_gives_no_count_never_a_guess():
    assert busy_ticks(STAT, {5}) is None
    assert busy_ticks("cpu  1 2 3 4\nintr 5\n") is None  # the total line alone is not a CPU's


def test_a_system_without_counters_records_none(tmp_path):
    assert read_busy_s(tmp_path / "no such file") is None
    (tmp_path / "stat").write_text("intr 1 2\n")
    assert read_busy_s(tmp_path / "stat") is None


def test_the_others_cpu_seconds_are_the_systems_busy_seconds_less_the_runs_own():
    # 10 s of wall time; the allowed CPUs busy for 35 s of CPU time, 15 of them this process's: 20 s others', 2 CPUs
    start, end = Sample(5.0, 2.0, 1000.0), Sample(15.0, 17.0, 1035.0)
    assert others_cpu_s(start, end) == 20.0
    assert other_load(others_cpu_s(start, end), end.wall_s - start.wall_s) == 2.0


def test_others_are_never_negative_and_unknown_where_either_sample_has_no_counters():
    assert others_cpu_s(Sample(0.0, 0.0, 10.0), Sample(1.0, 1.02, 11.0)) == 0.0  # ticks of 1/100 s: 1.0 < 1.02
    assert others_cpu_s(Sample(0.0, 0.0, None), Sample(1.0, 1.0, 5.0)) is None
    assert others_cpu_s(Sample(0.0, 0.0, 5.0), Sample(1.0, 1.0, None)) is None
    assert other_load(None, 10.0) is None
    assert other_load(3.0, 0.0) is None


def test_results_record_the_cpu_time_the_others_load_and_the_cpus():
    assert share_record(8.0, 6.5, 2.0, 2) == {"cpu_time_s": 6.5, "other_load": 0.25, "cpus": 2}
    assert share_record(8.0, 6.5, None, 2)["other_load"] is None


def test_a_busy_machine_is_said_in_one_line_from_two_samples():
    # 0.4 s apart: 1.0 s of busy CPU time, 0.2 of it this process's: others keep 0.8 / 0.4 = 2 CPUs busy
    line = busy_line(Sample(0.0, 0.0, 50.0), Sample(0.4, 0.2, 51.0), 2)
    assert line is not None and "\n" not in line
    assert "2.0 of the 2 CPUs" in line and "slower" in line and "shared" in line


def test_a_quiet_machine_or_one_without_counters_says_nothing():
    wall = 0.5  # values exact in binary: others' CPU seconds 0.25 over 0.5 s, exactly the threshold: not above it
    assert busy_line(Sample(0.0, 0.0, 50.0), Sample(wall, 0.25, 50.25 + BUSY_LOAD * wall), 2) is None
    assert busy_line(Sample(0.0, 0.0, 50.0), Sample(wall, 0.25, 50.5 + 0.125), 2) is not None  # 0.75 CPUs
    assert busy_line(Sample(0.0, 0.0, None), Sample(wall, 0.1, None), 2) is None


@pytest.mark.parametrize(("cpus", "jobs", "requested", "expected"), [
    (2, 1, None, 2),  # alone: every CPU it may use
    (2, 2, None, 1),  # two runs at once on 2 CPUs: one thread each
    (2, 3, None, 1),  # more jobs than CPUs: still one, never 0
    (16, 3, None, 5),  # 16 // 3
    (2, 2, 4, 2),  # the user's number, at most the CPUs (nerfexp.cpus)
    (8, 2, 4, 4),  # the user's number stands
    (1, 1, None, 1),
])
def test_threads_are_the_cpus_over_the_jobs_at_once_unless_asked_for(cpus, jobs, requested, expected):
    assert intra_op_threads(cpus, jobs, requested) == expected


@pytest.mark.parametrize(("cpus", "jobs", "requested", "busy", "expected"), [
    (2, 1, None, 2.0, 1),  # beside two single-threaded processes on 2 CPUs: one thread, never 0
    (2, 1, None, 0.6, 1),  # 0.6 of a CPU busy rounds to one
    (2, 1, None, 0.4, 2),  # less than half a CPU: not a CPU taken
    (16, 1, None, 5.8, 10),
    (4, 2, None, 2.0, 2),  # a multirun's siblings may be what is busy: its division stands
    (2, 1, 2, 2.0, 2),  # the user's number stands
])
def test_a_single_run_leaves_out_the_cpus_others_keep_busy(cpus, jobs, requested, busy, expected):
    assert intra_op_threads(cpus, jobs, requested, busy) == expected


def test_a_busy_start_sets_fewer_threads_and_says_why(monkeypatch, torch_threads):
    """Two samples 0.5 s apart, 1 CPU second of others' work: one CPU of two is busy, so one thread."""
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(machine_share, "available_cpus", lambda: 2)
    monkeypatch.setattr(machine_share, "BUSY_SAMPLE_S", 0.0)
    samples = iter([Sample(10.0, 1.0, 100.0), Sample(10.5, 1.0, 101.0)])
    monkeypatch.setattr(machine_share, "sample", lambda: next(samples))
    line, busy, _, _ = start_threads(None, None)
    assert torch.get_num_threads() == 1
    assert line == ("torch threads: 1 (auto: 2 CPUs this process may use, 2.0 of them busy with other processes; "
                    "threads=N sets it)")
    assert busy is not None and "2.0 of the 2 CPUs" in busy


@pytest.mark.parametrize(("launcher", "cpus", "expected"), [
    (None, 8, 1),  # a single run
    ({"_target_": "hydra._internal.core_plugins.basic_launcher.BasicLauncher"}, 8, 1),  # one job after another
    ({"_target_": JOBLIB, "n_jobs": 3}, 8, 3),
    ({"_target_": JOBLIB, "n_jobs": -1}, 8, 8),  # joblib's -1: one per CPU
    ({"_target_": JOBLIB, "n_jobs": -2}, 8, 7),  # all but one
    ({"_target_": JOBLIB, "n_jobs": -20}, 8, 1),
    ({"_target_": "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"}, 8, 1),
])
def test_the_jobs_a_multirun_starts_at_once(launcher, cpus, expected):
    assert parallel_jobs(launcher, cpus) == expected


def test_the_setting_wins_over_omp_num_threads_which_wins_over_auto():
    assert requested_threads(3, {"OMP_NUM_THREADS": "1"}) == 3
    assert requested_threads(None, {"OMP_NUM_THREADS": "2"}) == 2
    assert requested_threads(None, {"OMP_NUM_THREADS": "0"}) is None  # not a thread count
    assert requested_threads(None, {"OMP_NUM_THREADS": "two"}) is None
    assert requested_threads(None, {"OMP_NUM_THREADS": "\u0662"}) is None  # a digit, but not one OpenMP reads
    assert requested_threads(None, {"OMP_NUM_THREADS": "1000000000"}) == 1000000000  # capped where it is applied
    assert requested_threads(None, {}) is None


@pytest.fixture
def torch_threads():
    saved = torch.get_num_threads()
    yield
    torch.set_num_threads(saved)


def test_a_joblib_multirun_on_four_cpus_with_two_jobs_gives_each_two_threads(monkeypatch, torch_threads):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(machine_share, "available_cpus", lambda: 4)
    monkeypatch.setattr(machine_share, "BUSY_SAMPLE_S", 0.0)
    line, _, _, _ = start_threads(None, {"_target_": JOBLIB, "n_jobs": 2})
    assert torch.get_num_threads() == 2
    assert line == "torch threads: 2 (auto: 4 CPUs this process may use, 2 jobs at once; threads=N sets it)"
    line, _, _, _ = start_threads(1, {"_target_": JOBLIB, "n_jobs": 2})
    assert torch.get_num_threads() == 1 and "asked for" in line


@pytest.mark.parametrize(("threads", "cpus", "others_s", "expected"), [
    (2, 2, 12.0, (1, 1.2)),  # a neighbour came: 1.2 CPUs of others over 10 s
    (1, 2, 0.5, (2, 0.05)),  # it left
    (2, 2, 3.0, None),  # 0.3 of a CPU: not a CPU taken, the count stays
    (1, 2, 11.0, None),  # still there
    (4, 16, 20.0, (14, 2.0)),
    (1, 1, 30.0, None),  # one CPU: never fewer than one thread
])
def test_the_threads_follow_what_others_keep_busy(threads, cpus, others_s, expected):
    start, end = Sample(0.0, 0.0, 0.0), Sample(10.0, 8.0, 8.0 + others_s)  # the run's own 8 CPU seconds
    assert follow_load(threads, cpus, start, end) == expected


def test_without_counters_the_threads_stay():
    assert follow_load(2, 2, Sample(0.0, 0.0, None), Sample(10.0, 8.0, None)) is None


def follow(monkeypatch, samples: list[Sample], world_size: int = 1) -> tuple[ThreadsFollowLoad, list[dict]]:
    """A ``ThreadsFollowLoad`` for 2 CPUs run through ``len(samples) - 1`` training steps of a fake trainer, the
    machine read from ``samples`` in order (the first as training starts)."""
    readings = iter(samples)
    monkeypatch.setattr(callbacks, "sample", lambda: next(readings))
    changes: list[dict] = []
    follower = ThreadsFollowLoad(2, changes, window_s=10.0)
    trainer = SimpleNamespace(world_size=world_size, global_step=0)
    follower.on_train_start(trainer, None)
    for step in range(1, len(samples)):
        trainer.global_step = step
        follower.on_train_batch_end(trainer, None, None, None, step - 1)
    return follower, changes


def test_a_neighbour_that_comes_and_goes_takes_a_thread_and_gives_it_back(monkeypatch, torch_threads, caplog):
    torch.set_num_threads(2)
    # (wall, the run's own CPU seconds, the CPUs' busy seconds); at 6 s it is too soon to look
    samples = [Sample(0.0, 0.0, 0.0), Sample(6.0, 6.0, 6.0), Sample(12.0, 10.0, 24.4),
               Sample(22.0, 20.0, 45.4), Sample(32.0, 38.0, 63.6)]
    with caplog.at_level(logging.INFO, logger=callbacks.__name__):
        _, changes = follow(monkeypatch, samples)
    # step 2: 24.4 - 10 = 14.4 others' seconds over 12 s -> 1.2 CPUs: one thread; step 3: 21 - 10 = 11 over 10 s
    # -> stays; step 4: 18.2 - 18 = 0.2 over 10 s -> 0.02: two threads again
    assert changes == [{"step": 2, "threads": 1, "other_load": pytest.approx(1.2)},
                       {"step": 4, "threads": 2, "other_load": pytest.approx(0.02)}]
    assert torch.get_num_threads() == 2
    lines = [record.getMessage() for record in caplog.records]
    assert lines[0].startswith("torch threads: 2 -> 1 at step 2: other processes kept 1.2 of the 2 CPUs")
    assert caplog.records[0].levelno == logging.WARNING and caplog.records[1].levelno == logging.INFO


def test_a_distributed_run_never_looks(monkeypatch, torch_threads):
    torch.set_num_threads(2)
    _, changes = follow(monkeypatch, [Sample(0.0, 0.0, 0.0), Sample(20.0, 0.0, 40.0)], world_size=2)
    assert changes == [] and torch.get_num_threads() == 2


def test_a_run_follows_the_load_only_where_its_threads_were_chosen_for_it(monkeypatch, torch_threads):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(machine_share, "BUSY_SAMPLE_S", 0.0)
    monkeypatch.setattr(machine_share, "sample", lambda: Sample(0.0, 0.0, 0.0))
    assert start_threads(None, None).follows_load
    assert not start_threads(2, None).follows_load  # the user's number stands
    assert not start_threads(None, {"_target_": JOBLIB, "n_jobs": 2}).follows_load  # a multirun's division stands


@pytest.mark.parametrize(("setting", "environment", "asked"), [
    (64, "1", "threads=64"),  # a config written for a larger node: the setting wins over OMP_NUM_THREADS
    (THREAD_LIMIT, None, f"threads={THREAD_LIMIT}"),  # the most the settings check lets through
    (None, "1000000000", "OMP_NUM_THREADS=1000000000"),  # OpenMP would try to allocate for each and abort the process
    (None, str(2 ** 63 - 1), f"OMP_NUM_THREADS={2 ** 63 - 1}"),  # past what torch.set_num_threads takes
])
def test_a_thread_count_above_the_cpus_is_capped_at_them_with_a_line_naming_how_it_was_asked_for(
        monkeypatch, torch_threads, setting, environment, asked):
    monkeypatch.setattr(machine_share, "available_cpus", lambda: 2)
    monkeypatch.setattr(machine_share, "BUSY_SAMPLE_S", 0.0)
    if environment is None:
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    else:
        monkeypatch.setenv("OMP_NUM_THREADS", environment)
    choice = start_threads(setting, None)
    assert torch.get_num_threads() == 2 and choice.line.startswith("torch threads: 2 (asked for")
    assert choice.capped == (f"{asked}: more threads than the 2 CPUs this process may use; 2 run (threads beyond the "
                             "CPUs only wait on each other)")
    assert not choice.follows_load  # a number the user gave stands, capped


@pytest.mark.parametrize(("setting", "environment"), [(2, None), (None, "2"), (None, None), (1, "64")])
def test_a_thread_count_within_the_cpus_or_chosen_for_the_run_is_not_capped(monkeypatch, torch_threads, setting,
                                                                             environment):
    monkeypatch.setattr(machine_share, "available_cpus", lambda: 2)
    monkeypatch.setattr(machine_share, "BUSY_SAMPLE_S", 0.0)
    monkeypatch.setattr(machine_share, "sample", lambda: Sample(0.0, 0.0, None))
    if environment is None:
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    else:
        monkeypatch.setenv("OMP_NUM_THREADS", environment)
    choice = start_threads(setting, None)
    assert choice.capped is None and torch.get_num_threads() == (setting or 2)
