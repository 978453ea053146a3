"""Schedules: a value as a function of a step count (epsilon, learning rate, the importance
exponent), each a plain `Callable[[int], float]`."""

from __future__ import annotations

import math
from collections.abc import Callable


def linear_schedule(start: float, end: float, steps: int) -> Callable[[int], float]:
    """start -> end linearly over `steps`, then end. steps=0 gives the constant `end`."""
    if steps <= 0:
        return lambda t: end

    def value(t: int) -> float:
        return end + (start - end) * max(0.0, 1.0 - t / steps)

    return value


def exponential_schedule(start: float, end: float, decay: float) -> Callable[[int], float]:
    """start * decay ** t, floored at `end`: the Mario tutorial's epsilon, multiplied by
    `decay` once per env step (t = env steps so far, so it is the same at any env.num_envs)."""
    log_decay = math.log(decay)

    def value(t: int) -> float:
        return max(end, start * math.exp(log_decay * t))

    return value
