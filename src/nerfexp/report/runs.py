"""Reading a sweep's runs back: each job's state, overrides, results and validation curve, as data;
a file that cannot be read as nerfexp writes it (``nerfexp.rundir.records``: every field the report uses, typed
and bounded, and a results.json's fields as they stand to each other, ``relations_problem``) makes the run damaged,
never a wrong number. A finished run is ranked and compared only with its
test scores: one whose training collapsed, or whose results hold no finite test score, is listed as such."""


import functools
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from nerfexp.reading import UnreadableFile
from nerfexp.rundir.labels import NO_LABELS, is_notes, is_tags
from nerfexp.rundir.layout import (
    METRICS,
    RESULTS,
    STATUS,
    find_run_dirs,
    read_json,
    read_metrics,
)
from nerfexp.rundir.records import (
    METRICS_FIELDS,
    SCORES,
    STATUS_FIELDS,
    is_scored,
    record_problem,
    results_problem,
)
from nerfexp.rundir.state import status_state


@dataclass(frozen=True)
class Budget:
    """One scoring of a run's test views: after ``step`` optimizer steps, ``train_time_s`` seconds into its
    training; its scores (NaN or infinite: not scored, ``is_scored``)."""

    step: int
    train_time_s: float
    test_psnr: float
    test_ssim: float

    def score(self, metric: str) -> float:
        return getattr(self, f"test_{metric}")


def results_budgets(results: dict | None) -> list[Budget]:
    """A finished run's budgets (``nerfexp.report.budgets``) in step order, from its ``results``: its ``test_budgets``,
    or for an earlier nerfexp's run the one at its end (``steps``, ``train_time_s``, the top-level scores); none where
    it has neither (or is not finished: no ``results``)."""
    results = results or {}
    if "test_budgets" in results:
        return [Budget(b["step"], b["train_time_s"], b["test_psnr"], b["test_ssim"]) for b in results["test_budgets"]]
    if results.get("steps") is None or results.get("train_time_s") is None:
        return []
    return [Budget(results["steps"], results["train_time_s"], results["test_psnr"], results["test_ssim"])]


@dataclass
class Run:
    """One job's directory and what it left: ``state`` is finished, failed, running, killed, damaged, unknown,
    collapsed or not scored (finished without a test score: ``unscored``, whose reason is the ``detail``)."""

    path: Path
    state: str
    overrides: list[str] | None  # None: a damaged job whose overrides cannot be read
    detail: str = ""
    results: dict | None = None
    curve: list[tuple[int, float, float]] = field(default_factory=list)  # (step, wall seconds, validation PSNR)
    tags: list[str] = field(default_factory=list)  # its labels (nerfexp.rundir.labels)
    notes: str | None = None

    @functools.cached_property
    def budgets(self) -> list[Budget]:
        """Its budgets in step order (``results_budgets`` of its ``results``, read once: a report looks a run's budgets
        up at every budget of every comparison); none where it is not finished."""
        return results_budgets(self.results)


def run_precision(results: dict) -> str:
    """The precision a finished run trained in, from its results.json: ``precision``, else (an earlier
    nerfexp's) its recorded config's ``trainer.precision``; "unrecorded" where neither says."""
    trainer = (results.get("config") or {}).get("trainer") or {}
    recorded = results.get("precision", trainer.get("precision"))
    return "unrecorded" if recorded is None else str(recorded)


class Damaged(Exception):
    """A run's file that cannot be read as nerfexp writes it; the message names the file and why."""


def read_record(path: Path, problem: Callable[[object], str | None]) -> dict | None:
    """A run's JSON file (None where there is none) as nerfexp writes it (``problem`` of its data None: a
    ``nerfexp.rundir.records`` check), else ``Damaged`` naming the file and the problem."""
    try:
        record = read_json(path)
    except UnreadableFile as error:  # truncated, empty, not UTF-8, too large, unreadable
        raise Damaged(f"{path.name}: {error.reason}") from None
    if record is not None and (found := problem(record)) is not None:
        raise Damaged(f"{path.name}: {found}")
    return record


def read_curve(path: Path, ended: bool) -> list[tuple[int, float, float]]:
    """(step, wall seconds, validation PSNR) of each validation in a run's ``metrics.jsonl``, each line as
    nerfexp writes it (``METRICS_FIELDS``), else ``Damaged``; a last line cut short is damage where the run has
    ``ended`` (``read_metrics``)."""
    try:
        records = read_metrics(path, ended)
    except (ValueError, OSError) as error:
        raise Damaged(f"{METRICS}: {error}") from None
    for number, record in enumerate(records, 1):
        if (problem := record_problem(record, METRICS_FIELDS, ("step", "wall_time_s", "split", "psnr"))) is not None:
            raise Damaged(f"{METRICS}: line {number}: {problem}")
    return [(record["step"], record["wall_time_s"], record["psnr"]) for record in records if record["split"] == "val"]


def unscored(results: dict) -> str | None:
    """Why a finished run's ``results`` give no test score to rank or compare it by, or None: its training
    collapsed (``collapse``: the message), or a headline score (``SCORES``) is missing, null, NaN or infinite."""
    if results.get("collapse") is not None:
        return results["collapse"]
    for key in SCORES:
        if not is_scored(value := results.get(key)):
            return f"{RESULTS}: {key} is {'missing' if key not in results else value}: no test score to rank by"
    return None


def record_labels(name: str, record: dict) -> dict:
    """The labels (``nerfexp.rundir.labels``) a run's ``record`` (its file ``name``) holds, ``NO_LABELS`` where it
    has none (an earlier nerfexp's), else ``Damaged`` where one is not as nerfexp writes it."""
    labels = {**NO_LABELS, **{key: record[key] for key in NO_LABELS if key in record}}
    if not (is_tags(labels["tags"]) and is_notes(labels["notes"])):
        raise Damaged(f"{name}: tags or notes that are not as nerfexp writes them")
    return labels


def job_overrides(path: Path) -> list[str] | None:
    """A job's command-line overrides, from whichever of its ``status.json`` and ``results.json`` can be
    read (each records them), so that a job with another file damaged still counts against its variant;
    None where neither can."""
    for name in (STATUS, RESULTS):
        try:
            record = read_record(path / name, lambda record: None)
        except Damaged:
            continue
        overrides = (record or {}).get("overrides")
        if isinstance(overrides, list) and all(isinstance(o, str) for o in overrides):
            return overrides
    return None


def read_run(path: Path) -> Run:
    """What a run directory says about its job. A job whose status still says running but whose
    process is gone from this host was killed (out of memory, a time limit, a signal: ``nerfexp.rundir.state``,
    which every reader of a status shares). A run with a file
    that cannot be read as nerfexp writes it (``Damaged``) is listed as damaged with its overrides where
    they can be read (``job_overrides``; else none, and it joins no variant), and none of its numbers is
    used. Its labels are those of its results, else of its status."""
    try:
        status = read_record(path / STATUS, lambda record: record_problem(record, STATUS_FIELDS, ("state",))) or {}
        results = read_record(path / RESULTS, lambda record: results_problem(record, ("choices",)))
        labels = record_labels(*((RESULTS, results) if results is not None else (STATUS, status)))
    except Damaged as damage:
        return Run(path, "damaged", job_overrides(path), str(damage))
    overrides = status.get("overrides", (results or {}).get("overrides", []))
    state, detail = status_state(status)[:2] if status else ("finished" if results is not None else "unknown", "")
    if state == "finished" and results is None:
        state, detail = "failed", f"status says finished but {RESULTS} is missing"
    try:
        curve = read_curve(path, ended=state != "running")
    except Damaged as damage:
        ended = "" if state == "finished" else f" (the job {state}" + (f": {detail})" if detail else ")")
        return Run(path, "damaged", list(overrides), f"{damage}{ended}", **labels)
    if state == "finished" and (reason := unscored(results)) is not None:
        state, detail = ("collapsed" if results.get("collapse") is not None else "not scored"), reason
    return Run(path, state, list(overrides), detail, results if state == "finished" else None, curve, **labels)


def find_runs(directories: list[Path]) -> list[Run]:
    """Every run directory under ``directories`` (a run directory itself counts)."""
    paths = set()
    for directory in directories:
        if not directory.is_dir():
            raise SystemExit(f"nerfexp-report: error: {directory} is not a directory")
        paths.update(find_run_dirs(directory))
    if not paths:
        raise SystemExit(f"nerfexp-report: error: no runs (no {STATUS} or {RESULTS}) under "
                         f"{', '.join(map(str, directories))}")
    return [read_run(path) for path in sorted(paths)]
