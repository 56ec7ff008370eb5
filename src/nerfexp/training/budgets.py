"""Test scores at several budgets of one run: the test views scored, as the final test scores them, at chosen points
of training (``test_budgets``: fractions of its steps), so that a run says what it reached at a quarter or a half of
its budget without being trained again for it. ``nerfexp.training.recorders.RunRecorder`` scores them, outside its
training clock, and records each in ``results.json``'s ``test_budgets`` (docs/after-training.md).

Naming: a ``fraction`` is a share of the training's steps (0 < f < 1), a budget's ``step`` the optimizer steps
taken when it is scored (the weights after that many). Scoring never changes what is trained: the module's
random streams are forked around it (``score_test_views``), so that a run with budgets trains the same weights,
bit for bit, as one without.
"""

import contextlib
import math
from collections.abc import Iterator
from fractions import Fraction

import torch
from torch import nn

from nerfexp.training.perceptual import LPIPS_NAMES
from nerfexp.training.measures import ALWAYS_SCORED, image_means, image_scores

# The scores a budget records (each as ``test_{name}``, where ``measures.scored`` says every image has it)
BUDGET_SCORES = (*ALWAYS_SCORED, *LPIPS_NAMES)


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


def score_test_views(trainer, module) -> dict[int, dict[str, float]]:
    """Every test view scored with ``module``'s weights as they are now, exactly as the final test scores it:
    ``module.test_step`` on each batch of the data module's ``test_dataloader()`` (every view, in order), the
    batch converted and moved to the module's device as Lightning's test loop does, under inference mode and the
    precision plugin's test context, the module in evaluation mode. Returns ``{index: measures}``
    (``nerfexp.training.measures.image_scores``; a NonFiniteError where a view scored NaN).

    Nothing of training changes: each module's mode comes back (``evaluation_mode``) and torch's random streams
    are forked around it (``forked_random``: creating a loader's iterator draws its seed from them). No
    collective is called (``module.test_step`` directly, not through the distributed wrapper): under DDP each
    process scores every view itself, and none can wait on another."""
    scores: dict[int, dict[str, float]] = {}
    precision, strategy = trainer.precision_plugin, trainer.strategy
    with forked_random(module.device), evaluation_mode(module), torch.inference_mode():
        for batch_idx, batch in enumerate(trainer.datamodule.test_dataloader()):
            batch = strategy.batch_to_device(precision.convert_input(batch))
            with precision.test_step_context():
                outputs = module.test_step(batch, batch_idx)
            scores[outputs["index"]] = image_scores(outputs, "test", trainer.global_step)
    return scores
