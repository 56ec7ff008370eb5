"""The fields of a run's records, each with its rule (``nerfexp.domains``) as nerfexp writes it: ``results.json``
(``RESULTS_FIELDS``), ``status.json`` (``STATUS_FIELDS``) and each line of ``metrics.jsonl`` (``METRICS_FIELDS``).
A reader of a run directory (``nerfexp-report``, ``nerfexp-eval`` finding the checkpoint a run's test scored)
checks a record with ``record_problem`` before it uses a field, so that a record from elsewhere, or edited, whose
field is not as nerfexp writes it is named with its key and value, never a traceback or a wrong number.

Only the fields a reader uses are listed. A field left out is one an earlier nerfexp did not write (its reader's
default stands). A key with dots names a field inside mappings (``config.seed``); a mapping on its way that is
absent leaves the field absent, one that is not a mapping is the problem.

Numbers are bounded where their sums and means stop being numbers: counts, seconds and rates at 2^63 - 1
(``INTEGER_LIMIT``), a PSNR at ``PSNR_LIMIT``. A test score may also be NaN or infinite, as nerfexp writes it for
a render that was not finite or, a PSNR, an image rendered exactly (``is_scored`` tells a score from those).
"""

import math

from nerfexp.domains import (
    COUNT,
    INTEGER_LIMIT,
    NONNEGATIVE_COUNT,
    TEXT,
    Rule,
    breaks,
    choice,
    is_real,
    is_whole,
    list_of,
    optional,
    real,
    whole,
)
from nerfexp.nerf.appearance import PROTOCOLS
from nerfexp.rundir.labels import is_label_text

# The highest finite PSNR of 8-bit images: -10 log10 of the least mean squared error that is not 0, one colour
# level (1/255) in one channel of one pixel of an image of 3 (2^63 - 1) channels; a larger one is no PSNR
PSNR_LIMIT = -10 * math.log10((1 / 255) ** 2 / (3 * INTEGER_LIMIT))
PID_LIMIT = 2 ** 31 - 1  # a process id is a C int (pid_t)
SECONDS = real(0, INTEGER_LIMIT)
STATES = ("running", "finished", "failed")  # what status.json's state says (nerfexp.rundir.layout.write_status)
GIVEN, REFINED = "given", "refined"  # results.json's test_cameras (conf/test_cameras/)
# Other processes' mean busy CPUs (results.json's other_load) above which a run shared its machine: its times are
# partly its neighbours', and a report says so where it compares them (nerfexp.report.tables.shared_lines)
SHARED_LOAD = 0.25
SHA256 = ("64 hexadecimal digits", lambda v: isinstance(v, str) and len(v) == 64
          and all(c in "0123456789abcdef" for c in v))


def score(low: float, high: float, perfect: float | None = None) -> Rule:
    """A test score in [low, high], or, as a float, NaN (a render that was not finite) or ``perfect`` (the score
    of an image rendered exactly, where it is not finite: a PSNR's infinity); neither is a score (``is_scored``)."""
    beyond = "NaN" if perfect is None else f"NaN or {perfect}"
    return (f"a number in [{low:g}, {high:g}], or {beyond} (not scored)",
            lambda v: (isinstance(v, float) and (math.isnan(v) or v == perfect)) or (is_real(v) and low <= v <= high))


def is_scored(value) -> bool:
    """Whether a test score (``score``'s) is one: a finite number."""
    return is_real(value)


def is_line(value) -> bool:
    """A text of one line: none of its characters a control character (a newline, an escape sequence)."""
    return is_label_text(value, len(value)) if isinstance(value, str) else False


def is_choices(value) -> bool:
    """A run's choices: a mapping of config groups (and switches) to their values, each a text, a number, a
    boolean or null (never a container: the report groups runs by them)."""
    return isinstance(value, dict) and all(v is None or isinstance(v, str | bool) or is_real(v)
                                           for v in value.values())


PSNR, SSIM = score(0, PSNR_LIMIT, math.inf), score(-1, 1)
LPIPS = real(0, INTEGER_LIMIT)  # scored where present: nerfexp leaves LPIPS out where it did not score it
# The headline test scores: each a number a report ranks and compares by, where a run has it (``is_scored``)
SCORES = ("test_psnr", "test_ssim")
RESULTS_FIELDS: dict[str, Rule] = {
    "test_psnr": optional(PSNR, "not scored"),
    "test_ssim": optional(SSIM, "not scored"),
    "test_lpips": LPIPS,
    "test_psnr_right_half": PSNR,
    "test_ssim_right_half": SSIM,
    "test_views": list_of(NONNEGATIVE_COUNT),
    "test_psnr_per_view": list_of(PSNR),
    "test_ssim_per_view": list_of(SSIM),
    "test_lpips_per_view": list_of(LPIPS),
    "test_lpips_custom": LPIPS,  # a user's own AlexNet weights' (nerfexp.training.perceptual): never LPIPS
    "test_lpips_custom_per_view": list_of(LPIPS),
    "lpips_weights_sha256": SHA256,  # the AlexNet weights' file that scored either (nerfexp.report.lpips_weights)
    "test_protocol": choice(*PROTOCOLS),
    "test_cameras": choice(GIVEN, REFINED),
    "collapse": optional(("a text of one line", is_line), "the run did not collapse"),
    "choices": ("a mapping of config groups to their options (texts, numbers, booleans or null)", is_choices),
    "overrides": list_of(TEXT),
    "precision": TEXT,
    "config.seed": whole(-INTEGER_LIMIT - 1, INTEGER_LIMIT),
    "config.trainer.precision": ("a text or a whole number", lambda v: isinstance(v, str) or is_whole(v)),
    "machine": ("a mapping of texts host and device",
                lambda v: isinstance(v, dict) and TEXT[1](v.get("host")) and TEXT[1](v.get("device"))),
    "train_time_s": SECONDS,
    "steps": NONNEGATIVE_COUNT,
    "time_per_step_s": SECONDS,
    "rays_per_s": optional(real(0, INTEGER_LIMIT), "not measured"),
    "other_load": optional(real(0, INTEGER_LIMIT), "not measured"),  # nerfexp.training.machine_share
    "n_params": NONNEGATIVE_COUNT,
    "evaluations_per_ray": real(0, INTEGER_LIMIT),
    "checkpoint.path": TEXT,
    "checkpoint.sha256": SHA256,
    "test_budgets": ("a list of one or more mappings, one per budget", lambda v: isinstance(v, list) and v != []
                     and all(isinstance(budget, dict) for budget in v)),  # each: BUDGET_FIELDS (budgets_problem)
    "budget_scoring_s": SECONDS,
}
# The fields of each of results.json's test_budgets, the test scores at one budget as the final test scores them
# (a score NaN or infinite as the top-level scores may be: not scored); LPIPS only where it was scored
BUDGET_FIELDS: dict[str, Rule] = {
    "step": COUNT,
    "train_time_s": SECONDS,
    "evaluations": real(0, INTEGER_LIMIT),
    "test_psnr": PSNR,
    "test_ssim": SSIM,
    "test_lpips": LPIPS,
    "test_lpips_custom": LPIPS,
    "score_s": SECONDS,
}
BUDGET_REQUIRED = ("step", "train_time_s", "evaluations", "test_psnr", "test_ssim", "score_s")
CHECKPOINT_FIELDS = ("checkpoint.path", "checkpoint.sha256")  # the checkpoint a run's test scored
PER_VIEW = ("test_psnr_per_view", "test_ssim_per_view", "test_lpips_per_view",  # one item per test view
            "test_lpips_custom_per_view")
STATUS_FIELDS: dict[str, Rule] = {
    "state": choice(*STATES),
    "overrides": list_of(TEXT),
    "error": ("a text", lambda v: isinstance(v, str)),
    "host": TEXT,
    "pid": whole(1, PID_LIMIT),
    "process_start": optional(NONNEGATIVE_COUNT, "not recorded"),
    "signal": optional(TEXT, "none"),
}
METRICS_FIELDS: dict[str, Rule] = {
    "step": NONNEGATIVE_COUNT,
    "wall_time_s": SECONDS,
    "split": choice("val", "test"),
    "psnr": PSNR,
}
ABSENT = object()  # a field a record does not have


def lookup(record: dict, key: str) -> tuple[object, str | None]:
    """(the value of the field ``key`` of ``record``, None), following dots into mappings; (``ABSENT``, None)
    where it or a mapping on its way is absent; (``ABSENT``, the problem) where one on its way is not a mapping."""
    value, walked = record, []
    for part in key.split("."):
        if walked and not isinstance(value, dict):
            return ABSENT, f"key '{'.'.join(walked)}' is {value!r:.80}: expected a mapping"
        if part not in value:
            return ABSENT, None
        value = value[part]
        walked.append(part)
    return value, None


def record_problem(record: object, fields: dict[str, Rule], required: tuple[str, ...] = ()) -> str | None:
    """Why ``record`` (a JSON file's data) is not as nerfexp writes it, in words naming the key and its value,
    or None: it must be a mapping, hold the ``required`` keys, and every field of ``fields`` it has must keep its
    rule."""
    if not isinstance(record, dict):
        return f"not a mapping of keys (it is {record!r:.80})"
    for key in required:
        value, problem = lookup(record, key)
        if value is ABSENT:
            return problem or f"no key '{key}'"
    for key, rule in fields.items():
        value, problem = lookup(record, key)
        if problem is not None:
            return problem
        if value is not ABSENT and (wanted := breaks(rule, value)) is not None:
            return f"key '{key}' is {value!r:.80}: expected {wanted}"
    return None


def results_problem(results: object, required: tuple[str, ...] = ()) -> str | None:
    """``record_problem`` of a ``results.json`` (``RESULTS_FIELDS``), and its per-view scores one per test view."""
    if (problem := record_problem(results, RESULTS_FIELDS, required)) is not None:
        return problem
    views = results.get("test_views")
    for key in PER_VIEW:
        if key in results and (views is None or len(results[key]) != len(views)):
            count = "no test_views" if views is None else f"{len(views)} test_views"
            return f"key '{key}' has {len(results[key])} items for {count}: expected one per test view"
    return budgets_problem(results.get("test_budgets", []))


def budgets_problem(budgets: list[dict]) -> str | None:
    """Why a ``results.json``'s ``test_budgets`` (a list of mappings) are not as nerfexp writes them, naming the
    budget, its key and value, or None: each keeps ``BUDGET_FIELDS`` and has ``BUDGET_REQUIRED``; their steps
    increase and their training clock never goes back."""
    for i, budget in enumerate(budgets):
        if (problem := record_problem(budget, BUDGET_FIELDS, BUDGET_REQUIRED)) is not None:
            return f"key 'test_budgets', item {i}: {problem}"
    for i, (before, after) in enumerate(zip(budgets, budgets[1:]), 1):
        if after["step"] <= before["step"] or after["train_time_s"] < before["train_time_s"]:
            return (f"key 'test_budgets', item {i}: step {after['step']} at {after['train_time_s']!r} s after step "
                    f"{before['step']} at {before['train_time_s']!r} s: expected steps increasing and training "
                    "times never decreasing")
    return None


def checkpoint_problem(results: object) -> str | None:
    """``record_problem`` of a ``results.json`` for the checkpoint its test scored: where it names one, its path
    and SHA-256 (``CHECKPOINT_FIELDS``)."""
    named = CHECKPOINT_FIELDS if isinstance(results, dict) and "checkpoint" in results else ()
    return record_problem(results, {key: RESULTS_FIELDS[key] for key in CHECKPOINT_FIELDS}, named)
