"""CPU denormals flushed on every thread of torch's OpenMP team while training (``FlushDenormals``,
``nerfexp.denormals``): ``torch.set_flush_denormal`` alone reaches only the calling thread, and the team's
other threads kept IEEE denormals. Known content: a float32 denormal times 1 is 0 where the thread computing it
flushes, itself where it does not; a parallel operator splits a large tensor across the team's threads."""

import contextlib

import pytest
import torch

from nerfexp import denormals
from nerfexp.denormals import flushes_denormals, set_flush_denormal_everywhere
from nerfexp.training.callbacks import FlushDenormals

DENORMAL = 1e-39  # below float32's smallest normal number, 1.18e-38
SPLIT = 1 << 22  # elements: far above ATen's grain of 32,768, so every thread of the team takes a share


@contextlib.contextmanager
def threads(n: int):
    saved = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(saved)


def denormal_inputs() -> tuple[torch.Tensor, torch.Tensor]:
    """Made where nothing flushes (a flushing thread would store 0 for the denormal): x [SPLIT], all denormals, and
    a [256, 256] of 1e-20, each product of two of which, 1e-40, is a denormal."""
    x, a = torch.full((SPLIT,), DENORMAL), torch.full((256, 256), 1e-20)
    assert (x > 0).all()
    return x, a


def flushed_fraction(x: torch.Tensor, a: torch.Tensor) -> tuple[float, float]:
    """The fractions of the parallel elementwise product x * 1 and of the matrix product a @ a that came out 0."""
    return ((x * 1.0) == 0).float().mean().item(), ((a @ a) == 0).float().mean().item()


def test_torchs_own_call_leaves_the_other_threads_with_denormals_and_flush_denormals_reaches_them():
    inputs = denormal_inputs()
    with threads(2):
        assert flushed_fraction(*inputs) == (0.0, 0.0)  # IEEE everywhere; the team's second thread started here
        torch.set_flush_denormal(True)
        try:
            elementwise, product = flushed_fraction(*inputs)
            assert 0 < elementwise < 1 and 0 < product < 1  # the calling thread's share flushed, the other's not
        finally:
            torch.set_flush_denormal(False)
        callback = FlushDenormals()
        callback.on_fit_start(None, None)
        try:
            assert flushed_fraction(*inputs) == (1.0, 1.0)  # every thread flushes while training
        finally:
            callback.on_fit_end(None, None)
        assert flushed_fraction(*inputs) == (0.0, 0.0) and not flushes_denormals()  # every thread restored


def test_a_team_that_grows_again_while_training_flushes_on_every_thread():
    inputs = denormal_inputs()
    with threads(2):
        assert flushed_fraction(*inputs) == (0.0, 0.0)  # a second thread, kept by the runtime from here on
    with threads(1):  # a run that starts on one thread (a busy machine)
        assert set_flush_denormal_everywhere(True)
        try:
            with threads(2):  # ThreadsFollowLoad giving it a CPU back: the kept thread computes again
                assert flushed_fraction(*inputs) == (1.0, 1.0)
        finally:
            set_flush_denormal_everywhere(False)
    with threads(2):
        assert flushed_fraction(*inputs) == (0.0, 0.0)


def test_without_an_openmp_runtime_the_calling_thread_is_flushed_and_the_run_says_so(monkeypatch, caplog):
    monkeypatch.setattr(denormals, "openmp_runtime", lambda: None)
    callback = FlushDenormals()
    with caplog.at_level("INFO", logger="nerfexp.training.callbacks"):
        callback.on_fit_start(None, None)
    try:
        assert flushes_denormals()
        assert "CPU denormals flushed on the training thread only" in caplog.text
    finally:
        callback.on_fit_end(None, None)
    assert not flushes_denormals()


def test_the_runtime_found_is_the_one_torch_loaded():
    runtime = denormals.openmp_runtime()
    if torch.__config__.parallel_info().find("parallel backend: OpenMP") < 0:
        pytest.skip("this torch's parallel backend is not OpenMP")  # said, never silent: CI's torch is OpenMP
    assert runtime is not None and hasattr(runtime, "GOMP_parallel")
