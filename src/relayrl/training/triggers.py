"""Triggers: actions the loop fires every `interval` env steps (eval, policy save,
checkpoint, steps/s log). Batched envs advance by B steps, so a trigger fires once per
interval boundary crossed, never more."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass


@dataclass
class Progress:
    env_steps: int
    train_step: int


class IntervalTrigger:
    """Calls `fn(progress)` each time env steps cross a multiple of `interval` (0: never)."""

    def __init__(self, interval: int, fn: Callable[[Progress], None]) -> None:
        self.interval = interval
        self.fn = fn
        self._next = interval

    def start_at(self, env_steps: int) -> None:
        """Skip the boundaries already passed (after a resume)."""
        if self.interval > 0:
            self._next = (env_steps // self.interval + 1) * self.interval

    def __call__(self, progress: Progress) -> bool:
        if self.interval <= 0 or progress.env_steps < self._next:
            return False
        self._next = (progress.env_steps // self.interval + 1) * self.interval
        self.fn(progress)
        return True


class StepsPerSecond:
    """Env steps/s and gradient steps/s since the previous call."""

    def __init__(self) -> None:
        self._t = time.perf_counter()
        self._env = 0
        self._train = 0

    def reset(self, progress: Progress) -> None:
        self._t = time.perf_counter()
        self._env = progress.env_steps
        self._train = progress.train_step

    def __call__(self, progress: Progress) -> tuple[float, float]:
        now = time.perf_counter()
        dt = max(now - self._t, 1e-9)
        rates = ((progress.env_steps - self._env) / dt, (progress.train_step - self._train) / dt)
        self._t, self._env, self._train = now, progress.env_steps, progress.train_step
        return rates
