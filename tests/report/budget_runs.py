"""A sweep of hand-written runs with known test scores at two budgets, for the report's per-budget tests: a
reference and a variant whose verdict depends on the budget."""

import json
from pathlib import Path

from tests.helpers import make_run

# Reference "encoding=a" and variant "encoding=b", seeds 0, 1, 2, tested at steps 500 and 1,500. At 500 b is
# worse by 1.0, 1.1, 0.9 (resolved); at 1,500 by -0.5, +0.5, -0.1 (not resolved): the verdict depends on the budget.
REFERENCE = {0: [(500, 50.0, 20.0, 0.70), (1500, 150.0, 25.0, 0.80)],
             1: [(500, 52.0, 20.4, 0.72), (1500, 156.0, 25.6, 0.82)],
             2: [(500, 48.0, 19.8, 0.71), (1500, 144.0, 24.8, 0.81)]}
WORSE_EARLY = {0: [-1.0, -0.5], 1: [-1.1, 0.5], 2: [-0.9, -0.1]}  # b - a at steps 500, 1,500


def budget_sweep(root: Path, offsets: dict[int, list[float]] = WORSE_EARLY, time_scale: float = 1.0,
                 other_load: dict[str, float] | None = None) -> Path:
    """``encoding=a`` (the reference, ``REFERENCE``) and ``encoding=b`` (a's scores plus ``offsets``, its training
    times ``time_scale`` times a's); results.json's other_load of run NAME set to ``other_load[NAME]``."""
    for seed, budgets in REFERENCE.items():
        make_run(root, f"a{seed}", ["encoding=a", f"seed={seed}"], test_budgets=budgets)
        make_run(root, f"b{seed}", ["encoding=b", f"seed={seed}"],
                 test_budgets=[(step, t * time_scale, p + d, s) for (step, t, p, s), d in zip(budgets, offsets[seed])])
    for name, load in (other_load or {}).items():
        results = json.loads((root / name / "results.json").read_text())
        (root / name / "results.json").write_text(json.dumps({**results, "other_load": load}))
    return root
