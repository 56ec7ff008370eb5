"""What ``benchmarks/gpu/gpu_check.sh`` found, in one record: the machine (GPU, driver, torch, CUDA), each stage's exit
status and seconds, the device tests' counts (pytest's JUnit XML), and each timed variant's seconds per step, steps
per second and network evaluations per ray (``benchmarks/profiles/step_profile.py``'s files).

    python benchmarks/gpu/gpu_check_report.py machine WORK/machine.json
    python benchmarks/gpu/gpu_check_report.py summary WORK OUT      # OUT/gpu_check.json and OUT/gpu_check.md

WORK holds what the stages wrote: ``machine.json``, ``stages.tsv`` (stage, exit status, seconds: one line each),
``tests.xml`` and ``step_N.json`` (N: the variants' order). A stage that failed or timed out (exit status 124) is
recorded as such, and the others' figures still are.
"""

import json
import os
import platform
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

TIMED_OUT = 124  # timeout(1)'s exit status


def nvidia_smi() -> str | None:
    """The GPU's name, driver and memory as nvidia-smi says them, or None where it is missing or fails."""
    if shutil.which("nvidia-smi") is None:
        return None
    result = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"],
                            capture_output=True, text=True, timeout=60)
    return result.stdout.strip() if result.returncode == 0 else None


def machine() -> dict:
    """This machine as the figures need it said: GPU, its compute capability and memory, torch, its CUDA and cuDNN,
    Lightning, Python, the CPUs this process may use."""
    import torch

    record = {"python": platform.python_version(), "torch": torch.__version__, "cuda": torch.version.cuda,
              "cudnn": torch.backends.cudnn.version() if torch.backends.cudnn.is_available() else None,
              "cpus": len(os.sched_getaffinity(0)), "processor": platform.processor() or platform.machine(),
              "cuda_available": torch.cuda.is_available(), "nvidia_smi": nvidia_smi()}
    try:
        import lightning

        record["lightning"] = lightning.__version__
    except ImportError as error:
        record["lightning"] = f"missing ({error})"
    if torch.cuda.is_available():
        properties = torch.cuda.get_device_properties(0)
        record |= {"gpu": properties.name, "compute_capability": f"{properties.major}.{properties.minor}",
                   "gpu_memory_gib": round(properties.total_memory / 2**30, 1),
                   "multiprocessors": properties.multi_processor_count}
    return record


def read_stages(work: Path) -> list[dict]:
    """``stages.tsv``'s lines: each stage's name, exit status, seconds, and a word for the status."""
    stages = []
    path = work / "stages.tsv"
    for line in path.read_text().splitlines() if path.is_file() else []:
        name, status, seconds = line.split("\t")
        status = int(status)
        word = "ok" if status == 0 else "timed out" if status == TIMED_OUT else f"failed (exit {status})"
        stages.append({"stage": name, "exit": status, "seconds": int(seconds), "result": word})
    return stages


def read_tests(path: Path) -> dict | None:
    """pytest's JUnit XML as counts (tests, failures, errors, skipped, seconds) and the failed tests' names."""
    if not path.is_file():
        return None
    root = ET.parse(path).getroot()
    suites = [root] if root.tag == "testsuite" else list(root.iter("testsuite"))
    counts = {key: sum(int(suite.get(key, 0)) for suite in suites) for key in ("tests", "failures", "errors",
                                                                                "skipped")}
    counts["seconds"] = round(sum(float(suite.get("time", 0)) for suite in suites), 1)
    counts["failed"] = [f"{case.get('classname')}::{case.get('name')}" for case in root.iter("testcase")
                        if case.find("failure") is not None or case.find("error") is not None]
    return counts


def read_steps(work: Path) -> dict:
    """Each ``step_N.json`` (``step_profile.py``'s, one variant each), in the order run, as that variant's figures."""
    steps = {}
    for path in sorted(work.glob("step_*.json"), key=lambda path: int(path.stem.removeprefix("step_"))):
        for name, row in json.loads(path.read_text())["variants"].items():
            step_s = row["step_s"]
            steps[name] = {"overrides": row["overrides"], "device": row["device"], "precision": row["precision"],
                           "ms_per_step": round(1e3 * step_s, 2), "steps_per_s": round(1 / step_s, 1),
                           "evaluations_per_ray": round(row["evaluations_per_ray"], 1),
                           "top_ops_ms": row["top_ops_ms"]}
    return steps


def markdown(record: dict) -> str:
    m = record["machine"]
    lines = ["# benchmarks/gpu/gpu_check.sh", "",
             f"GPU: {m.get('gpu', 'none')} (compute capability {m.get('compute_capability', '-')}, "
             f"{m.get('gpu_memory_gib', '-')} GiB; nvidia-smi: {m.get('nvidia_smi')}); torch {m.get('torch')}, "
             f"CUDA {m.get('cuda')}, cuDNN {m.get('cudnn')}, Lightning {m.get('lightning')}, "
             f"Python {m.get('python')}, {m.get('cpus')} CPUs.", "", "| stage | result | seconds |", "|---|---|---|"]
    lines += [f"| {s['stage']} | {s['result']} | {s['seconds']} |" for s in record["stages"]]
    tests = record["tests"]
    if tests is not None:
        lines += ["", f"Device tests (`-m on_device`, NERFEXP_TEST_DEVICE={record['test_device']}): {tests['tests']} "
                      f"run, {tests['failures']} failed, {tests['errors']} errors, {tests['skipped']} skipped, in "
                      f"{tests['seconds']} s."]
        lines += [f"- failed: `{name}`" for name in tests["failed"]]
    if record["steps"]:
        lines += ["", "Training steps (Lightning's loop, `benchmarks/profiles/step_profile.py`: the mean over the "
                      "timed window, on a GPU the clock synchronized with it at both ends):", "",
                  "| variant | overrides | device | precision | ms / step | steps / s | evaluations / ray |",
                  "|---|---|---|---|---|---|---|"]
        lines += [f"| {name} | `{' '.join(s['overrides'])}` | {s['device']} | {s['precision']} | {s['ms_per_step']} | "
                  f"{s['steps_per_s']} | {s['evaluations_per_ray']} |" for name, s in record["steps"].items()]
        for name, s in record["steps"].items():
            lines += ["", f"{name}, ms per profiled step by operator: " +
                      ", ".join(f"`{op}` {ms}" for op, ms in s["top_ops_ms"].items())]
    return "\n".join(lines) + "\n"


def summary(work: Path, out: Path) -> dict:
    """The record of ``work``'s stages, written to OUT/gpu_check.json and .md."""
    machine_path = work / "machine.json"
    record = {"machine": json.loads(machine_path.read_text()) if machine_path.is_file() else {},
              "stages": read_stages(work), "test_device": os.environ.get("NERFEXP_TEST_DEVICE", "cpu"),
              "tests": read_tests(work / "tests.xml"), "steps": read_steps(work)}
    out.mkdir(parents=True, exist_ok=True)
    (out / "gpu_check.json").write_text(json.dumps(record, indent=2) + "\n")
    (out / "gpu_check.md").write_text(markdown(record))
    return record


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "machine":
        Path(sys.argv[2]).write_text(json.dumps(machine(), indent=2) + "\n")
    elif len(sys.argv) == 4 and sys.argv[1] == "summary":
        print(markdown(summary(Path(sys.argv[2]), Path(sys.argv[3]))), end="")
    else:
        sys.exit(__doc__.split("\n\n")[1])


if __name__ == "__main__":
    main()
