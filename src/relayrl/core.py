"""The protocols every layer speaks. Kept tiny on purpose, like Acme's core.py."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

import torch
from torch import nn

from relayrl.specs import Spec
from relayrl.types import Batch, StepOutput, Transition


@runtime_checkable
class Saveable(Protocol):
    """Anything whose state goes into a checkpoint as a plain dict."""

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> None: ...


class BatchedEnv(Protocol):
    """An environment that always works on a batch of `num_envs` >= 1 copies."""

    num_envs: int
    observation_spec: Spec
    action_spec: Spec

    def reset(self, seed: int | None = None) -> torch.Tensor:
        """Reset every copy; return observations [B, *obs_shape]."""
        ...

    def step(self, action: torch.Tensor) -> StepOutput:
        """Step every copy; copies whose episode ended are reset automatically."""
        ...

    def close(self) -> None: ...


class Policy(Protocol):
    """Maps a batch of observations to a batch of actions."""

    def __call__(self, obs: torch.Tensor) -> torch.Tensor: ...


class EnvActionPolicy(Policy, Protocol):
    """A policy whose actions are not what the env takes: PPO's continuous samples, which its
    rollouts keep (their log-probabilities are what its ratio needs) while the env receives
    them clipped or squashed into the bounds. The Actor steps the env with `env_action(action)`."""

    def env_action(self, action: torch.Tensor) -> torch.Tensor: ...


class Observer(Protocol):
    """Sees every batched transition the actor produces (metrics, replay writers)."""

    def __call__(self, transition: Transition) -> None: ...


class PreparesChunks(Protocol):
    """Optional for an Agent: work that stays valid for several gradient steps, done once for
    a chunk of them (DQN: its target network's Q-values of the next observations). A local
    uniform learner draws chunks of at most `prepare_horizon()` batches when that is > 0 and
    hands each chunk, as one Batch, to `prepare` before slicing it into the steps' batches."""

    def prepare_horizon(self) -> int:
        """How many of the next train() calls a chunk prepared now stays valid for (0: none)."""
        ...

    def prepare(self, batch: Batch, steps: int) -> Batch:
        """The chunk of the next `steps` batches, with what the agent computed ahead filled in
        (or as it is, where nothing stays valid that long)."""
        ...


class Agent(Saveable, Protocol):
    """What the train loop knows of an algorithm."""

    def collect_policy(self, env_step: Callable[[], int], network: nn.Module | None = None) -> Policy:
        """The exploring policy. `env_step` drives schedules (epsilon); `network` is the copy
        of `policy_network()` it runs (an actor's, kept fresh from a VariableContainer);
        None runs the agent's own network."""
        ...

    def policy_network(self) -> nn.Module:
        """The network whose weights actors need (Q-network, SAC actor)."""
        ...

    def eval_policy(self) -> Policy:
        """The greedy / deterministic policy."""
        ...

    def train(self, batch: Batch) -> dict[str, torch.Tensor]:
        """One gradient step; returns scalar metrics as tensors (no host sync forced)."""
        ...

    def policy_state(self) -> dict[str, Any]:
        """What `relayrl.load_policy` needs to rebuild the eval policy without the agent."""
        ...

    def scalars(self, env_steps: int) -> dict[str, float]:
        """Schedules' current values (epsilon, learning_rate), logged as TensorBoard's charts/<name>."""
        ...

    @property
    def train_step(self) -> int: ...
