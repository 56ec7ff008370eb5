"""The layers: import-linter checks the contracts in pyproject.toml (commands above training above the
run directory above data above the NeRF components and geometry above the helpers; ``nerf/`` pure torch)."""

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).parents[1]


def test_no_module_imports_from_a_layer_above_its_own():
    lint = Path(sys.executable).with_name("lint-imports")
    result = subprocess.run([str(lint), "--no-cache"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    assert "Contracts: 4 kept, 0 broken." in result.stdout
