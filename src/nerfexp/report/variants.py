"""Runs grouped into variants (the same overrides, apart from the seeds, tags, notes and test budgets), the reference
variant, and their differences paired by seed (``nerfexp.report.comparison``)."""


import math
import statistics
from collections import Counter
from dataclasses import dataclass

from nerfexp.report.comparison import PAIR, SEED, Difference, paired_difference
from nerfexp.report.runs import Run, run_precision
from nerfexp.rundir.labels import LABELS

# Keys that change how a run is scored or labelled, never what it trains: never part of a variant
NOT_TRAINED = (*LABELS, "test_budgets")


@dataclass
class Variant:
    """Runs that differ only in the override keys ``over`` (their seeds): ``by_seed`` pairs them with
    another variant's runs."""

    label: str
    runs: list[Run]
    over: tuple[str, ...] = ("seed",)

    @property
    def paired_by(self) -> str:
        """What its runs are matched on with another variant's, as the report counts them: ``SEED`` where only the
        seed is averaged over, else ``PAIR`` (over scenes, a seed on a scene)."""
        return SEED if tuple(self.over) == ("seed",) else PAIR

    @property
    def finished(self) -> list[Run]:
        return [run for run in self.runs if run.state == "finished"]

    def values(self, key: str) -> list[float]:
        return [run.results[key] for run in self.finished if run.results.get(key) is not None]

    def mean(self, key: str) -> float:
        values = self.values(key)
        return statistics.fmean(values) if values else math.nan

    def std(self, key: str) -> float:
        """Sample standard deviation (n - 1); NaN for fewer than two runs."""
        values = self.values(key)
        return statistics.stdev(values) if len(values) > 1 else math.nan

    def seed_of(self, run: Run) -> tuple[str, ...]:
        """The key that pairs ``run`` with another variant's runs: its overrides of the ``over`` keys."""
        return tuple(sorted(o for o in run.overrides if _key(o) in self.over))

    def by_seed(self, key: str) -> dict[tuple[str, ...], float]:
        """``results[key]`` of each finished run, keyed by ``seed_of`` the run."""
        return {self.seed_of(run): run.results[key] for run in self.finished if run.results.get(key) is not None}

    def choice(self, key: str):
        """The variant's choice of a config group, where all its finished runs agree."""
        values = {run.results["choices"].get(key) for run in self.finished}
        return values.pop() if len(values) == 1 else None

    @property
    def precision(self) -> str:
        """The precision its finished runs trained in (``run_precision``): one, or each with its count."""
        counts = Counter(run_precision(run.results) for run in self.finished)
        if len(counts) == 1:
            return next(iter(counts))
        return ", ".join(f"{precision} ({n})" for precision, n in sorted(counts.items()))

    @property
    def tags(self) -> list[str]:
        """Every tag of its runs (of all of them, finished or not), each once, in the order they are first met."""
        return list(dict.fromkeys(tag for run in self.runs for tag in run.tags))

    @property
    def notes(self) -> list[str]:
        """The notes of its runs, each different text once, in the order they are first met."""
        return list(dict.fromkeys(run.notes for run in self.runs if run.notes is not None))


def _key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("+~")


def group_variants(runs: list[Run], over: tuple[str, ...] = ("seed",)) -> list[Variant]:
    """Runs with the same overrides, apart from the keys in ``over``, ``test_budgets`` and the tags and notes
    (``nerfexp.rundir.labels``: what a run is for, not what it is), form a variant: every job started,
    damaged, failed or still running included, so that a variant counts its finished runs against all of
    them. Overrides that every run shares are left out of the labels. Variants are ranked by mean test PSNR."""
    kept = [tuple(o for o in run.overrides if _key(o) not in (*over, *NOT_TRAINED)) for run in runs]
    shared = set.intersection(*(set(k) for k in kept)) if kept else set()
    groups: dict[frozenset, tuple[tuple, list[Run]]] = {}  # the order of overrides does not matter
    for key, run in zip(kept, runs):
        groups.setdefault(frozenset(key), (key, []))[1].append(run)
    variants = []
    for key, members in groups.values():
        label = ", ".join(o for o in key if o not in shared) or ", ".join(key) or "default"
        variants.append(Variant(label, members, tuple(over)))
    return sorted(variants, key=lambda v: (-v.mean("test_psnr") if v.finished else math.inf, v.label))


def _override_set(label: str) -> frozenset[str]:
    """A label's overrides, in any order, with the values Hydra's grammar reads whatever their case (true,
    false, null) in lower case: ``"a=False, b=1"`` -> {"a=false", "b=1"}."""
    overrides = set()
    for part in label.split(","):
        key, equals, value = part.strip().partition("=")
        overrides.add(key + equals + (value.lower() if value.lower() in ("true", "false", "null") else value))
    return frozenset(overrides)


def reference_variant(variants: list[Variant], name: str | None = None) -> Variant | None:
    """The variant the others are compared with: the one named ``name`` (its label, or its overrides in
    any order; true, false and null in any case, as Hydra reads them), else the paper's complete model
    (``ablation=complete``) if one variant is, else None."""
    if name is not None:
        for variant in variants:
            if _override_set(variant.label) == _override_set(name):
                return variant
        raise SystemExit(f"nerfexp-report: error: --reference {name!r}: no such variant; the variants are "
                         + "; ".join(repr(v.label) for v in variants))
    complete = [v for v in variants if v.finished and v.choice("ablation") == "complete"]
    return complete[0] if len(complete) == 1 else None


def difference(a: Variant, b: Variant, key: str = "test_psnr") -> Difference:
    """a - b in ``key``, paired by seed (``nerfexp.report.comparison.paired_difference``)."""
    return paired_difference(a.by_seed(key), b.by_seed(key), a.paired_by)
