"""RolloutWriter: an actor's observer that gathers `steps` batched env steps and inserts them
into a table as ONE item, a rollout of [steps, B, ...] arrays, for an on-policy learner that
consumes each rollout once (a `Table.queue`, as Acme feeds its PPO learner).

An item's fields: obs, action, reward, next_obs (the true next observation, also at an
episode's end), terminated, truncated. A partly gathered rollout is not inserted: the run
collects whole rollouts between learner steps, so none is pending at a checkpoint.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from relayrl.arrays import to_numpy
from relayrl.replay.table import Table
from relayrl.types import Transition

FIELDS = ("obs", "action", "reward", "next_obs", "terminated", "truncated")


class RolloutWriter:
    def __init__(self, table: Table, steps: int) -> None:
        if steps < 1:
            raise ValueError(f"RolloutWriter: steps={steps} is not valid; it must be >= 1")
        self.table = table
        self.steps = steps
        self.filled = 0  # steps gathered into the rollout in progress
        self.arrays: dict[str, Any] = {}

    def __call__(self, transition: Transition) -> None:
        for name in FIELDS:
            value = self.as_array(getattr(transition, name))
            if self.filled == 0 and self.needs_buffer(name, value):
                self.arrays[name] = self.empty(value)
            self.arrays[name][self.filled] = value
        self.filled += 1
        if self.filled == self.steps:
            self.table.insert(dict(self.arrays))  # the default storage copies them (see needs_buffer)
            self.filled = 0

    # What a step's fields are gathered as; `rollouts_torch.TensorRolloutWriter` keeps tensors.
    def as_array(self, value: Any) -> Any:
        return to_numpy(value)

    def needs_buffer(self, name: str, value: Any) -> bool:
        """At a rollout's first step: a new buffer where the field's shape or dtype changed
        (the table's storage copies each rollout, so the buffers are reused)."""
        old = self.arrays.get(name)
        return old is None or tuple(old.shape[1:]) != tuple(value.shape) or old.dtype != value.dtype

    def empty(self, value: Any) -> Any:
        return np.empty((self.steps, *value.shape), dtype=value.dtype)

    def flush(self) -> None:
        """Nothing is staged between rollouts: a rollout goes in when its last step arrives."""

    def pending(self) -> int:
        """Steps of the rollout in progress (not yet in the table)."""
        return self.filled

    # What the local driver asks a replay writer when it resumes.
    def saved_episodes_intact(self) -> bool:
        return True

    def continue_episodes(self) -> None:
        """Episodes need no bookkeeping here: each rollout stands alone."""
