"""trainer.precision=auto against known hardware descriptions: the CPU flags that mean bf16 units, and the
config filled in place with what was chosen."""

import json
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


@pytest.mark.on_device  # benchmarks/gpu/gpu_check.sh runs it with the tests that take ``device``
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU: the CUDA rule is compute capability >= 8")
def test_auto_on_a_gpu_follows_its_compute_capability():
    major, _ = torch.cuda.get_device_capability()
    assert auto_precision("gpu")[0] == ("bf16-mixed" if major >= 8 else "32-true")


@pytest.mark.slow
def test_an_auto_run_records_and_resumes_in_the_precision_it_chose(tmp_path, tiny):
    run_dir = tmp_path / "run"
    result = run_nerfexp(*tiny, "scale.steps=30", "trainer.accelerator=cpu", "trainer.precision=auto",
                         f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    chosen = read_json(run_dir / "results.json")["precision"]  # by the CPU's units, and where it has some, measured
    assert chosen in ("32-true", "bf16-mixed") and f"trainer.precision=auto: {chosen} (" in result.stderr + result.stdout
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
    monkeypatch.setattr(precision, "measure_field", lambda cfg: (2.0, 1.0, 100))  # bf16 measured 2x faster
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


@pytest.fixture
def bf16_cpu(tmp_path, monkeypatch):
    """A CPU with bf16 units (faked) and an empty cache of measurements; the fields' steps measured: a list of
    each call's config."""
    (tmp_path / "cpuinfo").write_text(SAPPHIRE_RAPIDS)
    monkeypatch.setattr(precision, "CPUINFO", tmp_path / "cpuinfo")
    monkeypatch.setenv(precision.CACHE_VARIABLE, str(tmp_path / "cache"))
    return tmp_path / "cache"


@pytest.mark.parametrize(("float32_s", "bf16_s", "expected"), [
    (1.5, 1.0, "bf16-mixed"),  # 1.5x faster in bf16
    (1.05, 1.0, "32-true"),  # faster, but by less than MEASURED_MARGIN: float32's precision kept
    (1.0, 1.1, "32-true"),  # slower in bf16 (as on an Intel Xeon with AVX-512 BF16 and no AMX)
])
def test_auto_on_a_bf16_cpu_takes_bf16_only_where_the_fields_step_is_measured_faster(
        bf16_cpu, monkeypatch, caplog, float32_s, bf16_s, expected):
    monkeypatch.setattr(precision, "measure_field", lambda cfg: (float32_s, bf16_s, 123))
    cfg = tiny_config("trainer.accelerator=cpu", "trainer.precision=auto")
    with caplog.at_level(logging.INFO, logger="nerfexp"):
        fill_precision(cfg)
    assert cfg.trainer.precision == expected
    assert (f"a step of this run's field, 123 points, took {bf16_s:.4f} s in bf16 against {float32_s:.4f} s in "
            "float32 here (measured now;") in caplog.text


def test_a_measurement_is_kept_and_read_back_so_that_runs_of_one_config_choose_alike(bf16_cpu, monkeypatch):
    measured = []
    monkeypatch.setattr(precision, "measure_field", lambda cfg: measured.append(cfg) or (1.0, 2.0, 7))
    for seed in (5, 6):  # the seed is not what the step's time depends on
        cfg = tiny_config("trainer.accelerator=cpu", "trainer.precision=auto", f"seed={seed}")
        fill_precision(cfg)
        assert cfg.trainer.precision == "32-true"
    assert len(measured) == 1  # the second run read the first's measurement
    record = bf16_cpu / f"{precision.measured_key(cfg)}.json"
    assert json.loads(record.read_text()) == {"float32_s": 1.0, "bf16_s": 2.0, "points": 7}
    fill_precision(tiny_config("trainer.accelerator=cpu", "trainer.precision=auto", "scale.width=48"))
    assert len(measured) == 2  # another field: measured afresh
    record.write_text("{not json")  # a damaged record is measured again, never read as a choice
    fill_precision(tiny_config("trainer.accelerator=cpu", "trainer.precision=auto"))
    assert len(measured) == 3


def test_a_measurement_that_cannot_be_kept_says_so_naming_the_file(bf16_cpu, tmp_path, monkeypatch, caplog):
    # auto's choice stands (the measurement is this run's own) and its line says the record was not kept
    blocked = tmp_path / "a file"
    blocked.write_text("not a folder")
    monkeypatch.setenv(precision.CACHE_VARIABLE, str(blocked / "cache"))
    monkeypatch.setattr(precision, "measure_field", lambda cfg: (2.0, 1.0, 7))
    cfg = tiny_config("trainer.accelerator=cpu", "trainer.precision=auto")
    with caplog.at_level(logging.INFO, logger="nerfexp"):
        fill_precision(cfg)
    record = blocked / "cache" / f"{precision.measured_key(cfg)}.json"
    assert cfg.trainer.precision == "bf16-mixed"
    assert f"(measured now, not kept: {record} cannot be written (Not a directory); bf16 where" in caplog.text


def test_the_measured_step_is_the_runs_own_field_over_a_steps_points_on_forked_random_numbers(bf16_cpu):
    cfg = tiny_config("trainer.accelerator=cpu", "trainer.precision=auto")
    torch.manual_seed(3)
    expected_next = torch.rand(4)
    torch.manual_seed(3)
    float32_s, bf16_s, points = precision.measure_field(cfg)
    assert torch.equal(torch.rand(4), expected_next)  # the run's random numbers as they were
    assert float32_s > 0 and bf16_s > 0
    assert points == 256 * (16 + 16 + 16)  # TINY: 256 rays x (16 coarse + 32 fine samples)
    big = tiny_config("trainer.accelerator=cpu", "scale.batch_rays=4096")
    assert precision.measure_field(big)[2] == precision.MEASURED_POINTS


def test_components_that_say_autocast_slows_them_are_not_measured(bf16_cpu, monkeypatch):
    monkeypatch.setattr(precision, "measure_field", lambda cfg: pytest.fail("measured"))
    cfg = tiny_config("trainer.accelerator=cpu", "trainer.precision=auto", "encoding=hashgrid")
    fill_precision(cfg)
    assert cfg.trainer.precision == "32-true"
