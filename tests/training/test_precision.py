"""trainer.precision=auto against known hardware descriptions: the CPU flags that mean bf16 units, and the
config filled in place with what was chosen."""

import logging

import pytest
import torch
from omegaconf import OmegaConf

from nerfexp.rundir.trained import read_checkpoint
from nerfexp.training import precision
from nerfexp.training.precision import auto_precision, cpu_bf16_units, fill_precision
from tests.helpers import read_json, run_nerfexp, tiny_config

SAPPHIRE_RAPIDS = "processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f avx512_bf16 amx_bf16 amx_tile\n"
SKYLAKE = "processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f avx512bw\n"  # AVX-512 without bf16: emulated


def test_the_bf16_units_are_read_from_the_first_cpus_flags():
    assert cpu_bf16_units(SAPPHIRE_RAPIDS) == ["amx_bf16", "avx512_bf16"]
    assert cpu_bf16_units(SKYLAKE) == []
    assert cpu_bf16_units("processor\t: 0\n") == []  # no flags line (not x86)
    assert cpu_bf16_units("flags\t\t: avx512_bf16x\n") == []  # whole flags, not prefixes


@pytest.mark.parametrize(("cpuinfo", "expected"), [(SAPPHIRE_RAPIDS, "bf16-mixed"), (SKYLAKE, "32-true")])
def test_auto_on_the_cpu_follows_its_bf16_units(tmp_path, monkeypatch, caplog, cpuinfo, expected):
    (tmp_path / "cpuinfo").write_text(cpuinfo)
    monkeypatch.setattr(precision, "CPUINFO", tmp_path / "cpuinfo")
    cfg = OmegaConf.create({"trainer": {"accelerator": "cpu", "precision": "auto"}})
    OmegaConf.set_struct(cfg, True)
    with caplog.at_level(logging.INFO, logger="nerfexp"):
        fill_precision(cfg)
    assert cfg.trainer.precision == expected
    assert f"trainer.precision=auto: {expected} (this CPU has" in caplog.text


def test_a_machine_without_cpuinfo_keeps_float32(tmp_path, monkeypatch):
    monkeypatch.setattr(precision, "CPUINFO", tmp_path / "missing")
    assert auto_precision("cpu") == ("32-true", "this CPU's bf16 units are unknown (no /proc/cpuinfo)")


def test_a_precision_that_is_set_stays(tmp_path, monkeypatch):
    (tmp_path / "cpuinfo").write_text(SAPPHIRE_RAPIDS)
    monkeypatch.setattr(precision, "CPUINFO", tmp_path / "cpuinfo")
    for value in ("32-true", "bf16-mixed", "16-mixed"):
        cfg = OmegaConf.create({"trainer": {"accelerator": "cpu", "precision": value}})
        fill_precision(cfg)
        assert cfg.trainer.precision == value


@pytest.mark.on_device  # benchmarks/gpu_check.sh runs it with the tests that take ``device``
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU: the CUDA rule is compute capability >= 8")
def test_auto_on_a_gpu_follows_its_compute_capability():
    major, _ = torch.cuda.get_device_capability()
    assert auto_precision("gpu")[0] == ("bf16-mixed" if major >= 8 else "32-true")


@pytest.mark.slow
def test_an_auto_run_records_and_resumes_in_the_precision_it_chose(tmp_path, tiny):
    chosen, _ = auto_precision("cpu")
    run_dir = tmp_path / "run"
    result = run_nerfexp(*tiny, "scale.steps=30", "trainer.accelerator=cpu", "trainer.precision=auto",
                         f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert f"trainer.precision=auto: {chosen} (" in result.stderr + result.stdout
    assert read_json(run_dir / "results.json")["precision"] == chosen
    checkpoint = run_dir / "checkpoints" / "last.ckpt"
    assert read_checkpoint(checkpoint)["nerfexp_settings"]["settings"]["trainer.precision"] == chosen
    # the same machine chooses the same again: the checkpoint's recorded precision, so it may be continued
    result = run_nerfexp(*tiny, "scale.steps=40", "trainer.accelerator=cpu", "trainer.precision=auto",
                         f"resume={checkpoint}", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert read_json(run_dir / "results.json")["steps"] == 40


@pytest.mark.parametrize(("overrides", "expected"), [
    ((), "bf16-mixed"),  # the paper's field: bf16 autocast pays on a CPU with bf16 units
    (("encoding=hashgrid",), "32-true"),  # the hash encoding says autocast slows its step on a CPU
    (("experiment=fast", "trainer.precision=auto"), "32-true"),
])
def test_auto_on_a_bf16_cpu_keeps_float32_for_a_component_that_autocast_slows(tmp_path, monkeypatch, caplog,
                                                                                  overrides, expected):
    (tmp_path / "cpuinfo").write_text(SAPPHIRE_RAPIDS)
    monkeypatch.setattr(precision, "CPUINFO", tmp_path / "cpuinfo")
    cfg = tiny_config("trainer.accelerator=cpu", "trainer.precision=auto", *overrides)
    with caplog.at_level(logging.INFO, logger="nerfexp"):
        fill_precision(cfg)
    assert cfg.trainer.precision == expected
    if expected == "32-true":
        assert "but HashGridEncoding: bf16 autocast made a hash-grid step" in caplog.text


def test_the_component_rule_is_the_cpus_only(monkeypatch):
    """On a GPU with bf16 (faked) the hash encoding's CPU measurement does not apply."""
    monkeypatch.setattr(precision, "fast_bf16", lambda device: (True, f"a {device} with bf16"))
    targets = ["nerfexp.nerf.hashgrid.HashGridEncoding", "not.a.module.Class"]
    assert auto_precision("cuda", targets) == ("bf16-mixed", "a cuda with bf16")
    assert auto_precision("cpu", targets)[0] == "32-true"
    assert auto_precision("cpu", ["nerfexp.nerf.encodings.PositionalEncoding"]) == ("bf16-mixed", "a cpu with bf16")
