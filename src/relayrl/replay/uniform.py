"""An in-process ring buffer of transitions with uniform sampling.

The interface is small on purpose (`__call__` as an observer, `sample`, `size`,
`state_dict`) so a Reverb-style Table can take its place. Arrays are preallocated; writes go
through NumPy views because indexing torch tensors costs several times more per call on CPU.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from relayrl.specs import Spec
from relayrl.types import Batch, Transition


class UniformReplay:
    def __init__(self, capacity: int, obs_spec: Spec, action_spec: Spec, gamma: float, seed: int) -> None:
        self.capacity = capacity
        self.gamma = gamma
        self.obs = obs_spec.zeros(capacity)  # [C, *obs_shape]
        self.next_obs = obs_spec.zeros(capacity)  # [C, *obs_shape]
        self.action = action_spec.zeros(capacity)  # [C, *act_shape]
        self.reward = torch.zeros(capacity)  # [C]
        self.discount = torch.zeros(capacity)  # [C] gamma, or 0 after termination
        self._views = [t.numpy() for t in (self.obs, self.action, self.reward, self.next_obs, self.discount)]
        self._pos = 0
        self._size = 0
        self.rng = np.random.default_rng(seed)

    @property
    def size(self) -> int:
        return self._size

    def __call__(self, t: Transition) -> None:
        """Add a batch of B transitions (observer interface)."""
        b = t.reward.shape[0]
        # Bootstrap through truncation, never through termination.
        discount = np.where(t.terminated.numpy(), np.float32(0.0), np.float32(self.gamma))
        values = (t.obs.numpy(), t.action.numpy(), t.reward.numpy(), t.next_obs.numpy(), discount)
        end = self._pos + b
        if end <= self.capacity:
            for view, v in zip(self._views, values, strict=False):
                view[self._pos:end] = v
        else:  # wrap around
            idx = np.arange(self._pos, end) % self.capacity
            for view, v in zip(self._views, values, strict=False):
                view[idx] = v
        self._pos = end % self.capacity
        self._size = min(self._size + b, self.capacity)

    def sample(self, batch_size: int) -> Batch:
        if self._size == 0:
            raise RuntimeError("cannot sample from an empty replay")
        idx = self.rng.integers(0, self._size, batch_size)
        obs, action, reward, next_obs, discount = (torch.from_numpy(v[idx]) for v in self._views)
        return Batch(obs, action, reward, next_obs, discount, None)

    def state_dict(self) -> dict[str, Any]:
        n = self._size
        return {
            "arrays": [v[:n].copy() for v in self._views] if n < self.capacity else [v.copy() for v in self._views],
            "pos": self._pos,
            "size": n,
            "rng": self.rng.bit_generator.state,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        n = int(state["size"])
        if n > self.capacity:
            raise ValueError(f"checkpointed replay holds {n} items, more than capacity {self.capacity}")
        for view, arr in zip(self._views, state["arrays"], strict=False):
            view[: len(arr)] = arr
        self._pos = int(state["pos"])
        self._size = n
        self.rng.bit_generator.state = state["rng"]
