"""Learning-rate schedules as factors on a rate, one formula for every parameter group (the networks', and a
component's own, such as the pose corrections' ``camera_opt``)."""


def warmup_exponential_decay(step: int, max_steps: int, ratio: float, warmup: int) -> float:
    """The factor on a group's rate at ``step``: ramped up linearly over the first ``warmup`` steps (0: none),
    times ``ratio`` (final rate / rate) ** (step / max_steps), held at ``ratio`` past ``max_steps``:
    min(1, (step + 1) / warmup) ratio^min(step / max_steps, 1).

    >>> warmup_exponential_decay(50, 100, 0.01, 0)
    0.1
    """
    ramp = min((step + 1) / warmup, 1.0) if warmup > 0 else 1.0
    return ramp * ratio ** min(step / max_steps, 1.0)
