"""Test scores at several budgets of one run: the test views scored, as the final test scores them, at chosen points
of training (``test_budgets``: fractions of its steps), so that a run says what it reached at a quarter or a half of
its budget without being trained again for it. ``nerfexp.training.recorders.RunRecorder`` scores them, outside its
training clock, and records each in ``results.json``'s ``test_budgets`` (docs/after-training.md).

Naming: a ``fraction`` is a share of the training's steps (0 < f < 1), a budget's ``step`` the optimizer steps
taken when it is scored (the weights after that many). Scoring never changes what is trained: the module's
random streams are forked around it (``score_test_views``), so that a run with budgets trains the same weights,
bit for bit, as one without.

A budget costs what the final test costs, which a test protocol that fits something per view
(``test_cameras=refined``) makes many times a short run's training. So a budget's cost is measured before it is
paid: the first budget's first view is timed and multiplied by the views (a later budget: the last one's
scoring), and under ``test_budgets=auto`` (``DEFAULT_FRACTIONS``) the budgets are scored only while what they cost
in all stays within ``COST_SHARE`` of the training's estimated wall time (``affordable_budgets``); the others are
not scored, said in one line (``reduced_line``). A list the user gives is scored whatever it costs, with a line
where it costs more.
"""

import contextlib
import math
import time
from collections.abc import Callable, Iterator
from fractions import Fraction

import torch
from torch import nn

from nerfexp.scoring.measures import ALWAYS_SCORED, image_means, image_scores
from nerfexp.scoring.perceptual import LPIPS_NAMES

# The scores a budget records (each as ``test_{name}``, where ``measures.scored`` says every image has it)
BUDGET_SCORES = (*ALWAYS_SCORED, *LPIPS_NAMES)
AUTO = "auto"  # test_budgets=auto: DEFAULT_FRACTIONS, as many as COST_SHARE of the training's time pays for
DEFAULT_FRACTIONS = (0.25, 0.5)  # the budgets auto scores where their cost allows
COST_SHARE = 0.25  # auto's budgets cost at most this share of the training's estimated wall time, in all
SMALL_COST_S = 5.0  # budgets estimated to cost less than this many seconds in all are scored whatever the share


def budget_fractions(fractions: list[float], max_steps: int) -> dict[int, float]:
    """``{step: fraction}``: the step at which each of ``fractions`` (increasing, each in (0, 1)) of ``max_steps``
    is scored, ``max(1, round(f * max_steps))`` (Python's rounding: half to even), in order; a step two fractions
    give is the first's, and a step at or past ``max_steps`` is left out: the end is the final test's.

    >>> budget_fractions([0.25, 0.5], 4000), budget_fractions([0.1, 0.2, 0.9], 4)
    ({1000: 0.25, 2000: 0.5}, {1: 0.1})
    """
    steps: dict[int, float] = {}
    for fraction in fractions:
        step = max(1, round(fraction * max_steps))
        if step < max_steps:
            steps.setdefault(step, fraction)
    return steps


def budget_steps(fractions: list[float], max_steps: int) -> list[int]:
    """The steps at which the test views are scored during training, in order (``budget_fractions``).

    >>> budget_steps([0.25, 0.5], 4000), budget_steps([0.1, 0.2], 4), budget_steps([0.001, 0.002], 100)
    ([1000, 2000], [1], [1])
    """
    return list(budget_fractions(fractions, max_steps))


def training_estimate_s(elapsed_s: float, step: int, max_steps: int) -> float:
    """The training's whole wall time as estimated at ``step`` of ``max_steps`` from its clock then, ``elapsed_s``
    (budgets' scoring and kernel builds outside it): ``elapsed_s * max_steps / step``.

    >>> training_estimate_s(25.0, 375, 1500)
    100.0
    """
    return elapsed_s * max_steps / max(step, 1)


def affordable_budgets(pending: int, cost_each_s: float, spent_s: float, training_s: float) -> int:
    """How many of ``pending`` budgets, each estimated to cost ``cost_each_s`` seconds of scoring, ``test_budgets=auto``
    scores: as many as fit, with the ``spent_s`` seconds scoring has taken already, in ``COST_SHARE`` of the
    training's estimated ``training_s`` (or in ``SMALL_COST_S``, where that is more): floor((allowance - spent) /
    cost), between 0 and ``pending``.

    >>> affordable_budgets(2, 240.0, 0.0, 100.0), affordable_budgets(2, 10.0, 0.0, 100.0)
    (0, 2)
    >>> affordable_budgets(3, 10.0, 5.0, 100.0), affordable_budgets(2, 2.0, 0.0, 1.0)
    (2, 2)
    """
    allowance = max(COST_SHARE * training_s, SMALL_COST_S) - spent_s
    if cost_each_s <= 0:
        return pending
    return max(0, min(pending, math.floor(allowance / cost_each_s)))


def cost_text(cost_each_s: float, first_view_s: float | None, views: int) -> str:
    """How a budget's cost was estimated, in words: its first view's seconds times the views, or (``first_view_s``
    None) the last budget's scoring.

    >>> cost_text(240.0, 12.0, 20), cost_text(139.0, None, 20)
    ('about 240 s (its first view took 12.00 s, x 20 views)', 'about 139 s (the last budget took that)')
    """
    how = (f"its first view took {first_view_s:.2f} s, x {views} views" if first_view_s is not None
           else "the last budget took that")
    return f"about {cost_each_s:.0f} s ({how})"


def reduced_line(kept: list[float], dropped: list[float], cost: str, training_s: float) -> str:
    """The line ``test_budgets=auto`` says where it scores fewer budgets than ``DEFAULT_FRACTIONS``: what one is
    estimated to cost (``cost_text``), the share of the training's estimated ``training_s`` they may cost, which
    are ``dropped`` and which ``kept`` (the end always scored), and how to have them all.

    >>> line = reduced_line([0.25], [0.5], "about 30 s (the last budget took that)", 100.0)
    >>> "may cost 25% of the training's estimated 100 s in all: 1/2 not scored, the test views scored at 1/4" in line
    True
    """
    scored = f"at {', '.join(map(budget_text, kept))} and the end" if kept else "at the end alone"
    return (f"test_budgets=auto: a budget's scoring is estimated at {cost}, and the budgets may cost "
            f"{COST_SHARE:.0%} of the training's estimated {training_s:.0f} s in all: "
            f"{', '.join(map(budget_text, dropped))} not scored, the test views scored {scored} "
            f"(test_budgets=[...] scores a list whatever it costs; docs/after-training.md)")


def costly_line(fractions: list[float], cost: str, total_s: float, training_s: float) -> str:
    """The line a list of budgets the user gives says where their estimated cost (``cost`` each, ``total_s`` in
    all) is more than ``COST_SHARE`` of the training's estimated ``training_s``: they are all scored.

    >>> print(costly_line([0.25, 0.5], "about 240 s (...)", 480.0, 100.0)[:78])
    test_budgets=[0.25, 0.5]: a budget's scoring is estimated at about 240 s (...)
    """
    return (f"test_budgets=[{', '.join(f'{f:g}' for f in fractions)}]: a budget's scoring is estimated at {cost}, "
            f"about {total_s:.0f} s in all, more than {COST_SHARE:.0%} of the training's estimated {training_s:.0f} s: "
            f"scored as set, outside the training clock (results.json's budget_scoring_s)")


def budget_text(fraction: float) -> str:
    """A budget's fraction in words: a simple fraction (denominator up to 100) where it is one exactly, else the
    number.

    >>> budget_text(0.25), budget_text(0.1), budget_text(0.333)
    ('1/4', '1/10', '0.333')
    """
    simple = Fraction(fraction).limit_denominator(100)
    return f"{simple.numerator}/{simple.denominator}" if float(simple) == fraction else f"{fraction:g}"


def budget_entry(step: int, train_time_s: float, evaluations: float, scores: dict[int, dict[str, float]],
                 score_s: float) -> dict:
    """What ``results.json``'s ``test_budgets`` says of one budget: its ``step``, the training clock then
    (``train_time_s``), the network ``evaluations`` of training so far, the means over the test views ``scores``
    (``{index: measures}``) of ``BUDGET_SCORES`` as ``test_psnr``, ``test_ssim`` and ``test_lpips`` or
    ``test_lpips_custom`` where scored (absent otherwise, never NaN), and the wall seconds the scoring took
    (``score_s``)."""
    means = image_means(scores)
    return {"step": step, "train_time_s": train_time_s, "evaluations": evaluations,
            **{f"test_{name}": means[name] for name in BUDGET_SCORES if name in means}, "score_s": score_s}


def scoring_seconds(entries: list[dict]) -> float:
    """``results.json``'s ``budget_scoring_s``: the wall seconds all the mid-training budgets' scoring took, the
    end aside (the final test's, ``entries[-1]``)."""
    return math.fsum(entry["score_s"] for entry in entries[:-1])


@contextlib.contextmanager
def evaluation_mode(module: nn.Module) -> Iterator[None]:
    """Inside the block ``module`` and every module in it are in evaluation mode (no training-only noise, no
    training statistics kept); afterwards each is in the mode it was in before."""
    modes = [(part, part.training) for part in module.modules()]
    module.eval()
    try:
        yield
    finally:
        for part, training in modes:
            part.train(training)


@contextlib.contextmanager
def forked_random(device: torch.device) -> Iterator[None]:
    """Inside the block torch's random numbers may be drawn (CPU, and ``device``'s where it is a CUDA device):
    afterwards their states are as before, so that what training draws next is what it would have drawn."""
    with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
        yield


def score_test_views(trainer, module, go_on: Callable[[int, float, int], bool] | None = None
                     ) -> dict[int, dict[str, float]]:
    """Every test view scored with ``module``'s weights as they are now, exactly as the final test scores it:
    ``module.test_step`` on each batch of the data module's ``test_dataloader()`` (every view, in order), the
    batch converted and moved to the module's device as Lightning's test loop does, under inference mode and the
    precision plugin's test context, the module in evaluation mode. Returns ``{index: measures}``
    (``nerfexp.scoring.measures.image_scores``; a NonFiniteError where a view scored NaN). ``go_on(views scored,
    their seconds, views)``, where given, is asked after each view whether to score the next: where it says no,
    the views scored so far are returned (fewer than all).

    Nothing of training changes: each module's mode comes back (``evaluation_mode``) and torch's random streams
    are forked around it (``forked_random``: creating a loader's iterator draws its seed from them). No
    collective is called (``module.test_step`` directly, not through the distributed wrapper): under DDP each
    process scores every view itself, and none can wait on another."""
    scores: dict[int, dict[str, float]] = {}
    precision, strategy = trainer.precision_plugin, trainer.strategy
    started, loader = time.perf_counter(), trainer.datamodule.test_dataloader()
    with forked_random(module.device), evaluation_mode(module), torch.inference_mode():
        for batch_idx, batch in enumerate(loader):
            batch = strategy.batch_to_device(precision.convert_input(batch))
            with precision.test_step_context():
                outputs = module.test_step(batch, batch_idx)
            scores[outputs["index"]] = image_scores(outputs, "test", trainer.global_step)
            if go_on is not None and not go_on(len(scores), time.perf_counter() - started, len(loader)):
                break
    return scores
