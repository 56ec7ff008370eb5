"""The layers: import-linter checks the contracts in pyproject.toml (commands above training above the
run directory above data above the NeRF components and geometry above the helpers; ``nerf/`` pure torch); and
no module imports one that imports it back, however long the way round (type-checking imports included)."""

import os
import subprocess
import sys
from pathlib import Path

import grimp
import tomllib

REPO = Path(__file__).parents[1]


def test_no_module_imports_from_a_layer_above_its_own():
    # lint-imports' own entry point, by this interpreter: its script need not sit beside it (a virtual
    # environment over the system's packages has none)
    lint = "import sys; from importlinter.cli import lint_imports_command; sys.exit(lint_imports_command())"
    result = subprocess.run([sys.executable, "-c", lint, "--no-cache"], cwd=REPO, capture_output=True, text=True,
                            timeout=300, env={**os.environ, "COLUMNS": "1000"})  # a contract's name on one line
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    contracts = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    reported = " ".join(result.stdout.split())  # wrapped lines joined, should a terminal's width still wrap them
    assert contracts and all(f"{contract['name']} KEPT" in reported for contract in contracts), result.stdout[-4000:]


def test_no_module_imports_one_that_imports_it_back():
    graph = grimp.build_graph("nerfexp")  # import-linter's own graph of the package, type-checking imports included
    circles = [(module, *chain) for module in sorted(graph.modules)
               for imported in sorted(graph.find_modules_directly_imported_by(module))
               if (chain := graph.find_shortest_chain(importer=imported, imported=module)) is not None]
    assert len(graph.modules) > 100 and circles == [], circles[:3]  # the whole package read; its circles, if any
