"""What installing nerfexp gives: every imported package declared, the optional parts as extras with an
error naming the extra when one is missing, and a wheel built without warnings that holds every config."""

import ast
import importlib.metadata
import importlib.util
import json
import math
import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import setuptools
import tomllib
from omegaconf import OmegaConf

from nerfexp.commands import render
from nerfexp.commands.train import check_launcher
from nerfexp.extras import EXTRAS, MissingExtraError, require
from nerfexp.settings.checks import check_extras
from tests.helpers import REPO, TINY, command

PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())


def distribution_name(requirement: str) -> str:
    """``pycolmap==4.2.1`` -> ``pycolmap``; names compared as PEP 503 normalizes them."""
    return re.sub(r"[-_.]+", "-", re.match(r"[A-Za-z0-9_.\-]+", requirement).group()).lower()


def imported_top_levels() -> set[str]:
    """The top-level names of every module that nerfexp's source imports, anywhere in a file."""
    names = set()
    for path in (REPO / "src" / "nerfexp").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names.update(alias.name.split(".")[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names.add(node.module.split(".")[0])
    return names - set(sys.stdlib_module_names) - {"nerfexp"}


def test_every_imported_package_is_declared():
    declared = {distribution_name(r) for r in PYPROJECT["project"]["dependencies"]}
    extras = {distribution_name(r) for rs in PYPROJECT["project"]["optional-dependencies"].values() for r in rs}
    providers = importlib.metadata.packages_distributions()
    undeclared = {name: providers.get(name) for name in imported_top_levels()
                  if not {distribution_name(d) for d in providers.get(name, [])} & (declared | extras)}
    assert undeclared == {}
    assert {"pillow", "pyyaml"} <= declared  # imported as PIL and yaml


def test_lpips_needs_neither_torchvision_nor_the_lpips_package():
    # PyPI's torchvision wheels are CUDA builds: beside the CPU torch they fail to import (and would break
    # torchmetrics, which Lightning imports), and an unpinned one replaces torch (docs/metrics.md)
    assert not {"torchvision", "lpips"} & imported_top_levels()
    every = [*PYPROJECT["project"]["dependencies"], *sum(PYPROJECT["project"]["optional-dependencies"].values(), [])]
    assert not {"torchvision", "lpips"} & {distribution_name(r) for r in every}


def test_the_heavy_optional_parts_are_extras_the_tests_install():
    declared = {distribution_name(r) for r in PYPROJECT["project"]["dependencies"]}
    optional = PYPROJECT["project"]["optional-dependencies"]
    for module, extra in EXTRAS.items():
        (requirement,) = optional[extra]
        assert distribution_name(requirement) not in declared, requirement
        assert importlib.util.find_spec(module.split(".")[0]) is not None  # the dev install has it
    assert "nerfexp[all]" in optional["dev"] and set(EXTRAS.values()) <= set(re.findall(r"\w+", optional["all"][0]))


@pytest.mark.parametrize("cfg, module, message", [
    ({"data": {"_target_": "nerfexp.data.colmap.ColmapScene"}}, "pycolmap",
     'data=colmap needs pycolmap, which is not installed: pip install "nerfexp[colmap]"'),
    ({"data": {"_target_": "nerfexp.data.colmap.ColmapScene", "video": "clip.mp4"}}, "imageio_ffmpeg",
     'data.video needs imageio_ffmpeg, which is not installed: pip install "nerfexp[video]"'),
])
def test_a_config_needing_a_missing_extra_stops_in_one_line_naming_it(monkeypatch, cfg, module, message):
    check_extras(OmegaConf.create(cfg))  # installed: nothing to say
    monkeypatch.setitem(sys.modules, module, None)  # as if not installed: importing it fails
    with pytest.raises(MissingExtraError, match=re.escape(message)):
        check_extras(OmegaConf.create(cfg))


def test_the_submitit_launchers_and_render_name_their_extras(monkeypatch, capsys):
    check_launcher(["hydra/launcher=slurm", "seed=0,1"])
    monkeypatch.setitem(sys.modules, "hydra_plugins.hydra_submitit_launcher", None)
    check_launcher(["hydra/launcher=basic", "seed=0,1"])
    for argument in ("hydra/launcher=slurm", "hydra/launcher=submitit_local"):
        with pytest.raises(MissingExtraError, match=re.escape('pip install "nerfexp[slurm]"')):
            check_launcher([argument])
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)
    with pytest.raises(SystemExit, match=re.escape('nerfexp-render: error: nerfexp-render (its MP4 videos) needs '
                                                   'imageio_ffmpeg, which is not installed: '
                                                   'pip install "nerfexp[video]"')):
        render.main(["no/such/run"])


def test_a_missing_dependency_of_an_installed_extra_is_not_blamed_on_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "pycolmap", None)
    assert require("tomllib", "anything").loads("a = 1") == {"a": 1}
    with pytest.raises(KeyError):  # a module that is no extra's: a programming error, not a user's
        require("no_such_module_of_nerfexp", "anything")


def test_the_command_line_stops_before_making_a_run_directory(tmp_path):
    argv, env = command("nerfexp", "data=colmap", f"data.root={tmp_path}", f"hydra.run.dir={tmp_path / 'run'}")
    code = (f"import sys; sys.modules['pycolmap'] = None; sys.argv = {argv!r}; "
            "from nerfexp.commands.train import cli; cli()")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 1
    assert done.stderr.strip().splitlines() == [
        'nerfexp: error: data=colmap needs pycolmap, which is not installed: pip install "nerfexp[colmap]"']
    assert not (tmp_path / "run").exists()


def config_folders() -> set[str]:
    """``nerfexp.conf`` and one package name per folder below ``conf/`` (``sweeps/`` through its link)."""
    conf = REPO / "conf"
    return {".".join(("nerfexp", *Path(folder).relative_to(conf.parent).parts))
            for folder, _, _ in os.walk(conf, followlinks=True) if "__pycache__" not in folder}


def test_setuptools_finds_every_package_and_every_config_folder():
    find = PYPROJECT["tool"]["setuptools"]["packages"]["find"]  # found, never listed by hand
    (where,) = find["where"]
    found = set(setuptools.find_namespace_packages(REPO / where, exclude=find["exclude"]))
    code = {".".join(path.parent.relative_to(REPO / where).parts) for path in (REPO / where).rglob("__init__.py")
            if not path.is_relative_to(REPO / where / "nerfexp" / "conf")}  # the link to conf/
    assert {"nerfexp.settings", "nerfexp.nerf"} <= code
    assert found == code | config_folders()


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> tuple[Path, str]:
    """A wheel built from a copy of the tree (pip builds in the tree it is given), and pip's log."""
    folder = tmp_path_factory.mktemp("wheel")
    source = folder / "source"
    source.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, source / name)
    # src/nerfexp/conf, a link to conf/ (and conf/sweeps, one to sweeps/), copied as the folder it points to
    shutil.copytree(REPO / "src", source / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    done = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",  # no network
                           "-w", str(folder / "dist"), "-v", str(source)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    (built,) = (folder / "dist").glob("nerfexp-*.whl")
    return built, done.stdout + done.stderr


@pytest.mark.slow
def test_the_wheel_builds_without_warnings_and_holds_every_config(wheel):
    built, log = wheel
    assert not re.findall(r".*(?:is absent from the `packages`|Installing 'nerfexp[.\w]*' as data).*", log)
    names = set(zipfile.ZipFile(built).namelist())
    assert {"nerfexp/scoring/lpips_alex_v0.1.pth", "nerfexp/scoring/lpips_LICENSE.txt"} <= names  # LPIPS's heads
    kernels = {f"nerfexp/kernels/{path.name}" for path in (REPO / "src" / "nerfexp" / "kernels").glob("*.cpp")}
    assert len(kernels) >= 2 and kernels <= names  # the fused kernels' sources, built at first use
    in_wheel = {name for name in names if name.startswith("nerfexp/conf/")}
    configs = {"nerfexp/conf/" + os.path.relpath(os.path.join(folder, f), REPO / "conf").replace(os.sep, "/")
               for folder, _, files in os.walk(REPO / "conf", followlinks=True) for f in files if f.endswith(".yaml")}
    assert configs and configs <= in_wheel


@pytest.mark.slow
def test_the_wheel_installed_without_the_source_tree_runs(wheel, tmp_path):
    """Installed as a user installs it (not editable) into a fresh environment that reuses the installed
    dependencies: the help and a few steps of a tiny run, started outside the repository."""
    built, _ = wheel
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", "--without-pip", str(venv)], check=True)
    python, env = venv / "bin" / "python", {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    # --ignore-installed: beside (not over) the editable nerfexp of the system's site-packages, which the venv sees
    install = subprocess.run([str(python), "-m", "pip", "install", "--no-deps", "--no-index", "--ignore-installed",
                              str(built)], capture_output=True, text=True, env=env, timeout=300)
    assert install.returncode == 0, install.stderr[-3000:]
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    where = subprocess.run([str(python), "-c", "import nerfexp.conf, nerfexp.settings.checks; print(nerfexp.__file__)"],
                           cwd=elsewhere, capture_output=True, text=True, env=env, timeout=300)
    assert where.returncode == 0, where.stderr[-3000:]
    assert Path(where.stdout.strip()).is_relative_to(venv)  # the wheel's, not the repository's

    nerfexp = str(venv / "bin" / "nerfexp")
    shown = subprocess.run([nerfexp, "--help"], cwd=elsewhere, capture_output=True, text=True, env=env, timeout=300)
    assert shown.returncode == 0, shown.stderr[-3000:]
    assert "encoding" in shown.stdout and "view_dependence" in shown.stdout  # its config groups, read from the wheel
    run = subprocess.run([nerfexp, *TINY, "scale.steps=3", "scale.val_every=3", "hydra.run.dir=run"],
                         cwd=elsewhere, capture_output=True, text=True, env=env, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    results = json.loads((elsewhere / "run" / "results.json").read_text())
    assert results["steps"] == 3 and math.isfinite(results["test_psnr"])
