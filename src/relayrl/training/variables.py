"""VariableContainer: versioned policy weights the learner pushes and actors pull (TF-Agents'
variable container, as a plain object the Ray layer puts in a Ray actor). Weights travel as a
list of tensors, so applying them is one fused copy."""

from __future__ import annotations

import threading
from typing import Protocol

import torch
from torch import nn


def network_variables(network: nn.Module) -> list[torch.Tensor]:
    """What an actor's copy of `network` needs: its parameters, then its buffers (statistics
    the network keeps, such as PPO's observation normalisation)."""
    return [*network.parameters(), *network.buffers()]


class VariableContainer:
    """`copy=False` keeps references instead of CPU snapshots, on the weights' own device: right
    only where nothing updates the weights between a push and the pulls that follow it (the
    one-process loop, where the learner and the actor take turns), and it saves a copy of the
    weights per iteration (on a GPU, a copy to the host and back, which waits for the update)."""

    def __init__(self, copy: bool = True) -> None:
        self.copy = copy
        self._lock = threading.Lock()
        self.version = 0
        self._weights: list[torch.Tensor] | None = None

    def push(self, weights: list[torch.Tensor]) -> int:
        """Store `weights` (a CPU snapshot, or with copy=False references); returns the new version."""
        snapshot = [w.detach().to("cpu", copy=True) if self.copy else w.detach() for w in weights]
        with self._lock:
            self._weights = snapshot
            self.version += 1
            return self.version

    def pull(self, newer_than: int = 0) -> tuple[int, list[torch.Tensor] | None]:
        """(version, weights), or (version, None) when nothing newer than `newer_than` exists."""
        with self._lock:
            if self.version <= newer_than:
                return self.version, None
            return self.version, self._weights

    def state_dict(self) -> dict:
        return {"version": self.version, "weights": self._weights}

    def load_state_dict(self, state: dict) -> None:
        with self._lock:
            self.version, self._weights = int(state["version"]), state["weights"]


class WeightSource(Protocol):
    """What a WeightPuller pulls from: a VariableContainer, or a handle on one in another process."""

    def pull(self, newer_than: int = 0) -> tuple[int, list[torch.Tensor] | None]: ...


class WeightPuller:
    """Keeps an actor's copy of the policy network in step with a container.

    `maybe_pull()` copies the newest weights in place (so NumPy views of the parameters used
    for fast CPU inference stay valid) at most once every `interval` calls' worth of env steps.
    """

    def __init__(self, container: WeightSource, network: nn.Module, interval: int = 0) -> None:
        self.container = container
        self.params = [p.detach() for p in network_variables(network)]
        self.interval = interval
        self.version = 0
        self._last_pull_step = -(10**18)

    def maybe_pull(self, env_steps: int) -> bool:
        if env_steps - self._last_pull_step < self.interval:
            return False
        self._last_pull_step = env_steps
        version, weights = self.container.pull(newer_than=self.version)
        if weights is None:
            return False
        devices = {p.device for p in self.params}
        if devices != {torch.device("cpu")}:
            weights = [w.to(p.device) for w, p in zip(weights, self.params, strict=True)]
        torch._foreach_copy_(self.params, weights)
        self.version = version
        return True

    def state_dict(self) -> dict:
        """The acting copy and when it was pulled: with `interval` > 0 it may be older than the
        learner's weights, and a resumed run must act with the same one."""
        return {"version": self.version, "last_pull_step": self._last_pull_step,
                "params": [p.cpu().clone() for p in self.params]}

    def load_state_dict(self, state: dict) -> None:
        self.version = int(state["version"])
        self._last_pull_step = int(state["last_pull_step"])
        torch._foreach_copy_(self.params, [w.to(p.device) for w, p in zip(state["params"], self.params, strict=True)])
