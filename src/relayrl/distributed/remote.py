"""The learner's two remote ends, shaped like what `Learner` uses in one process: a table it
samples from and a variable container it pushes to. The Learner itself is unchanged."""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
import torch

from relayrl.core import Agent
from relayrl.replay import SampleInfo
from relayrl.training.variables import network_variables

SAMPLE_TIMEOUT_S = 0.5  # how long one sample RPC may wait on the rate limiter before returning empty


class RemoteTable:
    """Batches from the replay server, a group per RPC (up to `max_batches`); the next group
    is requested as soon as one arrives, so the server samples while the learner trains."""

    def __init__(self, server: Any, batch_size: int, max_batches: int = 16) -> None:
        self.server, self.batch_size, self.max_batches = server, batch_size, max_batches
        self._queue: deque[tuple[Any, SampleInfo]] = deque()
        self.pending: Any = None  # the outstanding sample RPC
        self.last_empty = False  # the latest reply held no batch: the rate limiter allowed none
        self.requests = 0  # sample requests sent
        self.answered = 0  # the number of the latest request answered

    def _request(self) -> None:
        self.pending = self.server.sample.remote(self.batch_size, self.max_batches, SAMPLE_TIMEOUT_S)
        self.requests += 1

    def poll(self) -> int:
        """Take in a reply if one came; returns the batches ready to train on."""
        import ray

        if self.pending is None:
            self._request()
        ready, _ = ray.wait([self.pending], timeout=0)
        if ready:
            got = ray.get(self.pending)
            self.answered = self.requests
            self.last_empty = not got
            # Ray hands back read-only views of its object store: copies are writable (torch warns
            # on read-only arrays) and free the store's buffers now, not when the batch is used.
            self._queue.extend((type(b)(*(None if x is None else torch.from_numpy(np.array(x)) for x in b)), info)
                               for b, info in got)
            self._request()
        return len(self._queue)

    def samples_available(self) -> int:
        return len(self._queue) * self.batch_size

    def sample(self, batch_size: int, timeout: float | None = None) -> tuple[Any, SampleInfo]:  # as Table.sample
        if not self._queue:
            raise RuntimeError("RemoteTable.sample: no batch fetched; call poll() first")
        return self._queue.popleft()

    def update_priorities(self, keys: np.ndarray, priorities: np.ndarray) -> None:
        self.server.update_priorities.remote(keys, priorities)  # no need to wait


class RemotePusher:
    """`push()` to the VariableContainer actor, at most once per `interval` gradient steps
    (each push ships the policy's weights), unless forced (before an evaluation). Weights no
    gradient step changed since the last push are not pushed again, forced or not: a new
    version always means new weights (an on-policy run drops rollouts of older versions)."""

    def __init__(self, handle: Any, agent: Agent, interval: int) -> None:
        self.handle, self.agent, self.interval = handle, agent, interval
        self.params = network_variables(agent.policy_network())
        self._last = -(10**18)
        self.last_ref: Any = None  # the latest push's ObjectRef; ray.get gives its version
        # the container's version after this pusher's pushes (each adds one): what a checkpoint keeps
        self.version = 0

    def push(self, weights: list[torch.Tensor] | None = None, force: bool = False) -> None:
        step = self.agent.train_step
        if step == self._last or (not force and step - self._last < self.interval):
            return
        self._last = step
        # Ray serializes the arguments now, so later in-place updates do not leak in.
        self.last_ref = self.handle.push.remote([w.detach().cpu() for w in (weights or self.params)])
        self.version += 1
