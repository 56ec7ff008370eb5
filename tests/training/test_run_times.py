"""A run's times as results.json records them: a fused kernel's one-off build is never training time (a fake
build moves the clock on by ``JUMP`` seconds, far more than a tiny run trains, so no timing is needed), and the
run records its CPU time, the others' load, the CPUs and the torch threads beside its wall time."""

import itertools
import json
import time

import pytest
import torch
from hydra.utils import instantiate

from nerfexp import kernels, machine_share
from nerfexp.kernels.cache import NotBuilt
from nerfexp.machine_share import Sample, available_cpus
from nerfexp.training import callbacks
from nerfexp.training.module import NeRFModule
from tests.helpers import run_nerfexp, tiny_config

JUMP = 1000.0  # seconds a fake build moves the clock on
SHORT = ["scale.steps=4", "scale.val_every=2"]


@pytest.fixture
def slow_builds(monkeypatch):
    """Every kernel "built" by a fake whose build moves ``time.perf_counter`` on by ``JUMP``; the names built, in
    order. Kernels are asked for afresh (the process's cache of them cleared before and after)."""
    offset, real, built = [0.0], time.perf_counter, []

    def build(name: str, source: bytes):
        built.append(name)
        offset[0] += JUMP
        return object(), True, None  # a module nothing calls: the default run encodes positions with posenc

    monkeypatch.setattr(time, "perf_counter", lambda: real() + offset[0])
    monkeypatch.setattr(kernels, "cached_kernel", build)
    monkeypatch.setattr(kernels, "_SPENT", {})
    monkeypatch.setattr(kernels, "_SAID", set())
    monkeypatch.delenv(kernels.SWITCH, raising=False)
    kernels._built.cache_clear()
    yield built
    kernels._built.cache_clear()


def train(tmp_path, tiny, *overrides: str) -> tuple[dict, list[dict], str]:
    result = run_nerfexp(*tiny, *SHORT, *overrides, f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    metrics = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    return json.loads((tmp_path / "results.json").read_text()), metrics, result.stdout + result.stderr


def test_the_kernels_a_run_uses_are_built_before_its_clock_starts_and_recorded_apart(
        tmp_path, tiny, slow_builds, monkeypatch):
    monkeypatch.setattr(NeRFModule, "kernels", lambda self: ["hash_encoding"])
    results, metrics, output = train(tmp_path, tiny)
    assert slow_builds == ["hash_encoding"]  # once, before training
    assert results["kernel_build_s"] >= JUMP
    assert results["train_time_s"] < JUMP and all(m["wall_time_s"] < JUMP for m in metrics)
    # the build said once, with its seconds, before the clock
    assert output.count("hash_encoding built in 1000 s") == 1
    assert "kernels, before the training clock started: hash_encoding built in 1000 s (cached for later runs)" in output


def fake_kernel(outcome: str):
    """A stand-in for ``nerfexp.kernels.cache.cached_kernel`` whose kernel is ``outcome``: built now, loaded from the
    cache, or not built."""
    def get(name: str, source: bytes):
        if outcome == "not built":
            raise NotBuilt("no C++ compiler: c++ not found")
        return object(), outcome == "built", None
    return get


# what a run's line says of its kernel (NeRFModule.kernels: hash_encoding) where it is built, loaded, not built or off
KERNEL_OUTCOMES = [
    ("built", "on", "hash_encoding built in 0 s (cached for later runs)"),
    ("loaded", "on", "hash_encoding loaded from the cache"),
    ("not built", "on", "hash_encoding not built (no C++ compiler: c++ not found): the torch path runs instead "
                        "(docs/acceleration.md)"),
    ("loaded", "off", "hash_encoding off (NERFEXP_KERNELS=off): the torch path runs instead"),
    ("built", "0", "hash_encoding off (NERFEXP_KERNELS=0): the torch path runs instead"),
]


@pytest.mark.parametrize(("outcome", "switch", "line"), KERNEL_OUTCOMES)
def test_the_kernels_line_says_what_each_came_to_never_ready_for_one_not_in_use(tmp_path, tiny, monkeypatch, outcome,
                                                                               switch, line):
    # the issue's case: with the kernels off or not built the log said "kernels hash_encoding ready before the
    # training clock started"
    monkeypatch.setattr(kernels, "cached_kernel", fake_kernel(outcome))
    monkeypatch.setattr(kernels, "_SPENT", {})
    monkeypatch.setattr(kernels, "_SAID", set())
    monkeypatch.setenv(kernels.SWITCH, switch)
    monkeypatch.setattr(NeRFModule, "kernels", lambda self: ["hash_encoding"])
    kernels._built.cache_clear()
    try:
        _, _, output = train(tmp_path, tiny)
    finally:
        kernels._built.cache_clear()
    assert f"kernels, before the training clock started: {line}\n" in output
    assert " ready " not in output and output.count("hash_encoding") == 1  # one line says it, once


def test_a_kernel_got_by_an_earlier_run_in_the_process_is_said_so(monkeypatch):
    # a multirun's jobs share a process: the second run's line does not claim the first run's build
    monkeypatch.setattr(kernels, "cached_kernel", fake_kernel("built"))
    monkeypatch.setattr(kernels, "_SPENT", {})
    monkeypatch.setattr(kernels, "_SAID", set())
    monkeypatch.delenv(kernels.SWITCH, raising=False)
    kernels._built.cache_clear()
    try:
        first, again = kernels.prepare(["lazy_adam"]), kernels.prepare(["lazy_adam", "lazy_adam"])
    finally:
        kernels._built.cache_clear()
    assert first == {"lazy_adam": "built in 0 s (cached for later runs)"}
    assert again == {"lazy_adam": "built in 0 s (cached for later runs) (got earlier in this process)"}


def test_a_kernel_first_asked_for_inside_the_clock_is_taken_out_of_it(tmp_path, tiny, slow_builds, monkeypatch):
    started = NeRFModule.on_train_batch_start

    def first_step_asks(self, batch, batch_idx):
        kernels.kernel("lazy_adam")  # a kernel no component declared, asked for at the first step
        return started(self, batch, batch_idx)

    monkeypatch.setattr(NeRFModule, "kernels", lambda self: [])
    monkeypatch.setattr(NeRFModule, "on_train_batch_start", first_step_asks)
    results, metrics, _ = train(tmp_path, tiny)
    assert slow_builds == ["lazy_adam"]
    assert results["kernel_build_s"] >= JUMP
    assert results["train_time_s"] < JUMP and all(m["wall_time_s"] < JUMP for m in metrics)


def test_a_run_records_its_cpu_time_the_others_load_its_cpus_and_threads(tmp_path, tiny, monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    results, _, output = train(tmp_path, tiny, "threads=2")  # the setting wins over OMP_NUM_THREADS
    assert results["torch_threads"] == 2 and "torch threads: 2 (asked for" in output
    assert results["cpu_time_s"] > 0 and results["cpus"] == available_cpus()
    assert results["other_load"] is None or results["other_load"] >= 0  # None only without /proc/stat
    assert results["kernel_build_s"] == 0.0  # the default model runs no fused kernel


def test_a_thread_count_above_the_cpus_asked_for_by_omp_num_threads_is_capped_with_a_line(tmp_path, tiny,
                                                                                         monkeypatch):
    # OMP_NUM_THREADS, which torch and OpenMP read too, is not refused: a run caps it at the CPUs and says so (10^9
    # threads made OpenMP abort the process, leaving its status.json saying running)
    monkeypatch.setenv("OMP_NUM_THREADS", "1000000000")
    saved = torch.get_num_threads()
    try:
        results, _, output = train(tmp_path, tiny)
    finally:
        torch.set_num_threads(saved)
    cpus = available_cpus()
    assert results["torch_threads"] == cpus and f"torch threads: {cpus} (asked for" in output
    assert (f"OMP_NUM_THREADS=1000000000: more threads than the {cpus} CPUs this process may use; {cpus} run"
            in output)
    assert json.loads((tmp_path / "status.json").read_text())["state"] == "finished"


@pytest.mark.parametrize(("overrides", "expected"), [
    ([], []),  # the positional encoding runs no fused kernel
    (["encoding=hashgrid"], ["hash_encoding"]),
    (["encoding=hashgrid", "encoding.position.sparse_gradients=true",
      "model.optimizer._target_=nerfexp.training.optimizers.LazyAdam"], ["hash_encoding", "lazy_adam"]),
])
def test_a_model_names_the_kernels_its_training_runs_on_a_cpu(overrides, expected):
    model = instantiate(tiny_config(*overrides).model)
    assert model.kernels() == expected
    model.to(torch.float64)  # tables no longer float32: the fused kernels would not run
    assert model.kernels() == []


def test_a_busy_start_that_passes_gives_the_run_its_threads_back(tmp_path, tiny, monkeypatch):
    """The start sees every CPU busy (one thread); the machine read while training, every sample 10 s of wall time
    after the last with nothing else running: the run takes the CPUs back at its first step, says so and records it."""
    cpus = available_cpus()
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(machine_share, "BUSY_SAMPLE_S", 0.0)
    start = iter([Sample(0.0, 0.0, 0.0), Sample(1.0, 0.0, float(cpus))])  # others kept every CPU busy
    monkeypatch.setattr(machine_share, "sample", lambda: next(start))
    ticks = itertools.count()
    monkeypatch.setattr(callbacks, "sample", lambda: Sample(10.0 * next(ticks), 0.0, 0.0))
    saved = torch.get_num_threads()
    try:
        results, _, output = train(tmp_path, tiny)
    finally:
        torch.set_num_threads(saved)
    assert results["torch_threads"] == 1 and "the machine is already busy" in output
    if cpus > 1:
        assert results["thread_changes"] == [{"step": 1, "threads": cpus, "other_load": 0.0}]
        assert f"torch threads: 1 -> {cpus} at step 1" in output
    else:
        assert results["thread_changes"] == []
