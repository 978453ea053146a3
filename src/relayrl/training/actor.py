"""Actor: runs a policy in a batched env and feeds every transition to its observers."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from relayrl.core import BatchedEnv, Observer, Policy
from relayrl.training.variables import WeightPuller
from relayrl.types import Transition


class Actor:
    """env + policy + observers. `run(n)` takes at least `n` env steps (B per batched step).

    Observers with a `flush()` (replay writers) are flushed at the end of every run. With a
    `puller`, each run starts by pulling newer policy weights (every `interval` env steps).
    """

    def __init__(self, env: BatchedEnv, policy: Policy, observers: Sequence[Observer],
                 seed: int | None = None, puller: WeightPuller | None = None) -> None:
        self.env = env
        self.policy = policy
        self.puller = puller  # refreshes the policy's weights from a VariableContainer
        self.observers = list(observers)
        self.env_steps = 0
        self._obs: torch.Tensor = env.reset(seed=seed)

    def run(self, num_steps: int) -> None:
        if self.puller is not None:
            self.puller.maybe_pull(self.env_steps)
        b = self.env.num_envs
        taken = 0
        while taken < num_steps:
            obs = self._obs
            action = self.policy(obs)
            out = self.env.step(action)
            t = Transition(obs, action, out.reward, out.next_obs, out.terminated, out.truncated)
            for observer in self.observers:
                observer(t)
            self._obs = out.obs
            taken += b
        self.env_steps += taken
        for observer in self.observers:
            flush = getattr(observer, "flush", None)
            if flush is not None:
                flush()  # staged steps reach the replay before anyone samples
