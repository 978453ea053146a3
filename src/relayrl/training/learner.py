"""Learner: samples batches from a replay Table and runs the agent's gradient steps."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any, cast

import numpy as np
import torch

from relayrl.core import Agent
from relayrl.errors import NonFiniteError
from relayrl.replay import SampleInfo, Table
from relayrl.replay.rate_limiters import UNLIMITED
from relayrl.training.finite import DIVERGED, describe
from relayrl.training.triggers import IntervalTrigger, Progress
from relayrl.training.variables import VariableContainer, network_variables

SAMPLE_CHUNK_BATCHES = 128  # batches drawn per `Table.sample` call in a uniform burst


class Learner:
    """agent + table. `learn(k)` takes k gradient steps, firing `triggers` after each one, then
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
        self.variables = variables  # receives the policy weights after every learn() with a step
        self._policy_params = network_variables(agent.policy_network())
        self.table = table
        self.batch_size = batch_size
        self.device = device
        self.prioritized = prioritized
        self.importance_exponent = importance_exponent
        self.priority_eps = priority_eps
        self.last_metrics: dict[str, torch.Tensor] = {}
        self._chunk: int | None = None  # batches per `sample` call in a uniform burst, set at the first

    def available_steps(self) -> int:
        """Gradient steps the table's rate limiter allows now. A limiter that sets no rate
        (MinSize, the Table's default, once the table holds its minimum) allows any number:
        there `learn(n)` takes the steps wanted, and asking this is refused in one line."""
        available = self.table.samples_available()
        if available >= UNLIMITED:
            raise ValueError("the table's rate limiter sets no samples-per-insert rate (MinSize: any number of "
                             "samples once it holds its minimum), so no number of steps is 'available': call "
                             "learn(n) with the gradient steps wanted, or give the table a SampleToInsertRatio")
        return available // self.batch_size

    def _batches(self, iterations: int) -> Iterator[tuple[Any, SampleInfo]]:
        """`iterations` sampled batches. From a uniform local table, a burst is drawn with one
        `sample` call per chunk and sliced, which spreads the table's fixed cost per call over the
        chunk. In the one-process loop nothing is inserted
        during a burst, so these are the items of one call per batch (the same RNG draws);
        where another thread inserts meanwhile, its items become sampleable at the next chunk
        instead of the next batch. Prioritized batches depend on the priorities the previous
        step set, so they are drawn one by one. The agent gets each chunk first, cut at its
        `prepare_horizon()` where that is > 0, and fills in what it can compute once for the
        whole chunk (`Agent.prepare`: DQN with a target network)."""
        if self.prioritized or iterations == 1 or not isinstance(self.table, Table) or self.table.max_times_sampled:
            for _ in range(iterations):
                yield self.table.sample(self.batch_size)
            return
        n = self.batch_size
        while iterations > 0:
            k = min(iterations, self._chunk or 1)  # the first call learns the batch's size
            h = self.agent.prepare_horizon()
            if h > 0:
                k = min(k, h)  # a chunk ends where what the agent prepares goes stale
            batch, info = self.table.sample(k * n)
            if self._chunk is None:  # at most ~32 MB a call: bursts of pixel batches stay small
                nbytes = sum(x.nbytes for x in batch if isinstance(x, torch.Tensor))
                self._chunk = max(1, min(SAMPLE_CHUNK_BATCHES, (32 << 20) // max(1, nbytes)))
            batch = self.agent.prepare(batch, k)  # what stays valid for the chunk, computed once
            for j in range(k):
                rows = slice(j * n, (j + 1) * n)
                # cast: a NamedTuple's class, built from its fields (mypy takes it for tuple's, of one iterable)
                yield (cast(Any, type(batch))(*(x[rows] if isinstance(x, torch.Tensor) else x for x in batch)),
                       SampleInfo(info.key[rows], info.probability[rows], info.table_size, info.priority[rows]))
            iterations -= k

    def learn(self, iterations: int) -> None:
        for batch, info in self._batches(iterations):
            if self.prioritized:
                w = np.power(info.table_size * info.probability, -self.importance_exponent)  # [N]
                batch = batch._replace(weight=torch.from_numpy((w / w.max()).astype(np.float32)))
            if self.device.type != "cpu" and isinstance(batch, tuple):  # a rollout (dict) is moved by its agent
                # cast: a NamedTuple's class, built from its fields (mypy takes it for tuple's, of one iterable)
                batch = cast(Any, type(batch))(*(None if x is None else x.to(self.device, non_blocking=True)
                                                 for x in batch))
            self.last_metrics = self.agent.train(batch)
            if self.prioritized:
                td = self.last_metrics["td_error"].abs().cpu().numpy().astype(np.float64)
                if not np.isfinite(td).all():  # on the host already: the check costs no sync
                    raise NonFiniteError(f"the TD error was {describe(float(td[~np.isfinite(td)][0]))} at train step "
                                         f"{self.agent.train_step:,}: {DIVERGED}")
                self.table.update_priorities(info.key, td + self.priority_eps)
            if self.triggers:
                progress = Progress(self.env_steps(), self.agent.train_step)
                for trigger in self.triggers:
                    trigger(progress)
        if iterations > 0 and self.variables is not None:
            self.variables.push(self._policy_params)

    def scalar_metrics(self) -> dict[str, float]:
        """Latest training scalars as floats, named like CleanRL's `losses/...`."""
        return {f"losses/{k}": float(v.abs().mean() if k == "td_error" else v.float().mean())
                for k, v in self.last_metrics.items()}
