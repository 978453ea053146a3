"""Learner: samples batches from a replay Table and runs the agent's gradient steps."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch

from relayrl.core import Agent
from relayrl.replay import Table
from relayrl.training.triggers import IntervalTrigger, Progress
from relayrl.training.variables import VariableContainer
from relayrl.types import Batch


class Learner:
    """agent + table. `run(k)` takes k gradient steps, firing `triggers` after each one, then
    pushes the policy weights to the VariableContainer if it has one; `last_metrics` holds
    the latest scalars.

    With a prioritized table (`prioritized=True`) each batch carries importance weights
    w_i = (N * P(i)) ** -importance_exponent / max_j w_j (Schaul et al. 2016, normalised by
    the batch maximum), and the sampled items get |td error| + priority_eps as new priorities.
    """

    def __init__(self, agent: Agent, table: Table, batch_size: int, device: torch.device,
                 prioritized: bool = False, importance_exponent: float = 0.4, priority_eps: float = 1e-6,
                 variables: VariableContainer | None = None, triggers: Sequence[IntervalTrigger] = (),
                 env_steps: Callable[[], int] | None = None) -> None:
        self.agent = agent
        self.triggers = list(triggers)  # fired after every gradient step
        self.env_steps = env_steps or (lambda: 0)  # what triggers see as Progress.env_steps
        self.variables = variables  # receives the policy weights after every run with a step
        self._policy_params = list(agent.policy_network().parameters())
        self.table = table
        self.batch_size = batch_size
        self.device = device
        self.prioritized = prioritized
        self.importance_exponent = importance_exponent
        self.priority_eps = priority_eps
        self.last_metrics: dict[str, torch.Tensor] = {}

    def available_steps(self) -> int:
        """Gradient steps the table's rate limiter allows now."""
        return self.table.samples_available() // self.batch_size

    def run(self, iterations: int) -> None:
        for _ in range(iterations):
            batch, info = self.table.sample(self.batch_size)
            if self.prioritized:
                w = np.power(info.table_size * info.probability, -self.importance_exponent)  # [N]
                batch = batch._replace(weight=torch.from_numpy((w / w.max()).astype(np.float32)))
            if self.device.type != "cpu":
                batch = Batch(*(None if x is None else x.to(self.device, non_blocking=True) for x in batch))
            self.last_metrics = self.agent.train(batch)
            if self.prioritized:
                td = self.last_metrics["td_error"].abs().cpu().numpy().astype(np.float64)
                self.table.update_priorities(info.key, td + self.priority_eps)
            if self.triggers:
                progress = Progress(self.env_steps(), self.agent.train_step)
                for trigger in self.triggers:
                    trigger(progress)
        if iterations > 0 and self.variables is not None:
            self.variables.push(self._policy_params)

    def scalar_metrics(self) -> dict[str, float]:
        """Latest training scalars as floats, named like CleanRL's `losses/...`."""
        out = {}
        for k, v in self.last_metrics.items():
            out[f"losses/{k}"] = float(v.abs().mean() if k == "td_error" else v.float().mean())
        return out
