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
# partly its neighbours', and a report says so where it compares them (nerfexp.report.shared_machines.timing_caveats)
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
    "test_lpips_custom": LPIPS,  # a user's own AlexNet weights' (nerfexp.scoring.perceptual): never LPIPS
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
    "other_load": optional(real(0, INTEGER_LIMIT), "not measured"),  # nerfexp.machine_share
    "n_params": NONNEGATIVE_COUNT,
    "evaluations_per_ray": real(0, INTEGER_LIMIT),
    "checkpoint.path": TEXT,
    "checkpoint.sha256": SHA256,
    "test_budgets": ("a list of one or more mappings, one per budget", lambda v: isinstance(v, list) and v != []
                     and all(isinstance(budget, dict) for budget in v)),  # each: BUDGET_FIELDS (budgets_problem)
    "budget_scoring_s": SECONDS,
    "test_resolution": list_of(COUNT, 2),  # [width, height] of the test images
    "split": TEXT,  # how a rule split the views (the scene's own files: absent)
    "scene.name": TEXT,  # a scene by name: the cache's record of it (nerfexp.data.scene_cache.SCENE_KEYS)
    "scene.catalog": TEXT,
    "scene.sha256": SHA256,
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
    return budgets_problem(results.get("test_budgets", [])) or relations_problem(results)


def budgets_problem(budgets: list[dict]) -> str | None:
    """Why a ``results.json``'s ``test_budgets`` (a list of mappings) are not as nerfexp writes them, naming the
    budget, its key and value, or None: each keeps ``BUDGET_FIELDS`` and has ``BUDGET_REQUIRED`` (how they stand to
    each other and to the run: ``relations_problem``)."""
    for i, budget in enumerate(budgets):
        if (problem := record_problem(budget, BUDGET_FIELDS, BUDGET_REQUIRED)) is not None:
            return f"key 'test_budgets', item {i}: {problem}"
    return None


# The headline test scores that the last of results.json's test_budgets, the end, repeats (each in both or in neither)
END_SCORES = ("test_psnr", "test_ssim", "test_lpips", "test_lpips_custom")
# Two float64 computations of one number (a mean in another order, a quotient) agree to this, relative to the number
AGREE = 1e-9


def same(a, b) -> bool:
    """Whether two of a results.json's values are one number written twice: equal, NaN being the same as NaN."""
    return a == b or (isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b))


def agree(a, b) -> bool:
    """Whether two computations of one number agree (``same``, or finite and within ``AGREE`` of the larger)."""
    return same(a, b) or (is_real(a) and is_real(b) and abs(a - b) <= AGREE * max(1.0, abs(a), abs(b)))


def mean(values: list) -> float:
    """The mean of a results.json's per-view scores as nerfexp takes it (NaN of none; infinite or NaN where one is)."""
    return math.fsum(values) / len(values) if values else math.nan


def steps_problem(results: dict) -> str | None:
    """Where ``test_budgets`` go back (a step not after the one before, or a training time before its), or past the
    run's last step (``steps``)."""
    budgets, steps = results.get("test_budgets", []), results.get("steps")
    for i, (before, after) in enumerate(zip(budgets, budgets[1:]), 1):
        if after["step"] <= before["step"] or after["train_time_s"] < before["train_time_s"]:
            return (f"key 'test_budgets', item {i}: step {after['step']} at {after['train_time_s']!r} s after step "
                    f"{before['step']} at {before['train_time_s']!r} s: expected steps increasing and training "
                    "times never decreasing")
    for i, budget in enumerate(budgets):
        if steps is not None and budget["step"] > steps:
            return (f"key 'test_budgets', item {i} says step {budget['step']}, but the run ended at step {steps} "
                    "(key 'steps'): expected every budget within the run's steps")
    return None


def end_problem(results: dict) -> str | None:
    """Where the last of ``test_budgets`` is not the run's end: at another step than ``steps``, another time than
    ``train_time_s``, or with other scores than the headline ones (``END_SCORES``, each in both or in neither)."""
    if not (budgets := results.get("test_budgets")):
        return None
    end = budgets[-1]
    clocks = [(key, headline) for key, headline in (("step", "steps"), ("train_time_s", "train_time_s"))
              if headline in results]  # where the run says when it ended
    for key, headline in [*clocks, *((key, key) for key in END_SCORES)]:
        if not same(end.get(key), results.get(headline)):
            return (f"key 'test_budgets', item {len(budgets) - 1}, the last, says {key} {end.get(key)!r}, but key "
                    f"'{headline}' is {results.get(headline)!r}: expected the last budget to be the run's end, with "
                    "its headline numbers")
    return None


def scoring_problem(results: dict) -> str | None:
    """Where ``budget_scoring_s`` is not the sum of the ``score_s`` of the budgets before the end."""
    if "budget_scoring_s" not in results or not (budgets := results.get("test_budgets")):
        return None
    spent = math.fsum(budget["score_s"] for budget in budgets[:-1])
    if agree(results["budget_scoring_s"], spent):
        return None
    return (f"key 'budget_scoring_s' is {results['budget_scoring_s']!r}, but the budgets before the end took "
            f"{spent!r} s (key 'test_budgets', their score_s): expected the sum")


def time_per_step_problem(results: dict) -> str | None:
    """Where ``time_per_step_s`` is not ``train_time_s / max(1, steps)``."""
    if not all(results.get(key) is not None for key in ("time_per_step_s", "train_time_s", "steps")):
        return None
    seconds, steps = results["train_time_s"], results["steps"]
    if agree(results["time_per_step_s"], quotient := seconds / max(steps, 1)):
        return None
    return (f"key 'time_per_step_s' is {results['time_per_step_s']!r}, but key 'train_time_s' / max(1, key 'steps') "
            f"is {seconds!r} / max(1, {steps}) = {quotient!r}: expected the quotient")


def views_problem(results: dict) -> str | None:
    """Where a headline score with per-view scores (``PER_VIEW``) is not their mean."""
    for key in PER_VIEW:
        headline = key.removesuffix("_per_view")
        if key in results and not agree(results.get(headline), mean(results[key])):
            return (f"key '{headline}' is {results.get(headline)!r}, but the mean of key '{key}' is "
                    f"{mean(results[key])!r}: expected the mean of the views' scores")
    return None


# The relations nerfexp's writer (nerfexp.training.recorders.RunRecorder.on_test_epoch_end) keeps between the fields
# of a results.json, each a check naming the keys it finds broken (relations_problem)
RELATIONS = (steps_problem, end_problem, scoring_problem, time_per_step_problem, views_problem)


def relations_problem(results: dict) -> str | None:
    """Why a ``results.json`` (its fields each as nerfexp writes them: ``record_problem``) contradicts itself, naming
    the keys, their values and the relation broken (the first of ``RELATIONS``), or None. nerfexp's writer keeps
    every one, and a report compares a run by them; one broken was edited, or mixed from two runs:

    - ``test_budgets``: their steps increase and their training times never decrease, none after the run's last step
      (``steps``), and the last is the end: at step ``steps`` and ``train_time_s`` seconds, with the headline scores
      (``END_SCORES``, each in both or in neither);
    - ``budget_scoring_s`` is the sum of the ``score_s`` of the budgets before the end;
    - ``time_per_step_s`` is ``train_time_s / max(1, steps)``;
    - a headline score with per-view scores (``test_psnr_per_view``, ...) is their mean."""
    return next((problem for relation in RELATIONS if (problem := relation(results)) is not None), None)


def checkpoint_problem(results: object) -> str | None:
    """``record_problem`` of a ``results.json`` for the checkpoint its test scored: where it names one, its path
    and SHA-256 (``CHECKPOINT_FIELDS``)."""
    named = CHECKPOINT_FIELDS if isinstance(results, dict) and "checkpoint" in results else ()
    return record_problem(results, {key: RESULTS_FIELDS[key] for key in CHECKPOINT_FIELDS}, named)
