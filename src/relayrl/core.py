"""The protocols every layer speaks. Kept tiny on purpose, like Acme's core.py.

Each protocol lists every method the loop calls. Where a capability is optional the protocol
holds its default, the "nothing to do" or "not supported" answer, and a class inherits it by
subclassing the protocol (`class DQNAgent(Agent)`), so callers call the method directly
instead of probing for it.
"""

from __future__ import annotations

import functools
import types
from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

import torch
from torch import nn

from relayrl.specs import Spec
from relayrl.types import Batch, StepOutput, Transition


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

    def get_state(self) -> list[bytes] | None:
        """Every copy's state mid-episode, for a checkpoint. None (the default): the env cannot
        be saved (simulator handles), and a resumed run starts new episodes."""
        return None

    def state_problem(self) -> str | None:
        """Why `get_state` gives None, where the env knows (a copy that cannot be pickled says
        why); None otherwise."""
        return None

    def set_state(self, states: list[bytes]) -> None:
        """Restore what `get_state` returned. Only called with a state `get_state` gave."""
        # The name first: mypy reads a body that only raises NotImplementedError as abstract, and
        # envs that cannot save (AleBatchEnv) inherit this one.
        name = type(self).__name__
        raise NotImplementedError(f"{name} cannot restore its copies' state")


@runtime_checkable
class Policy(Protocol):
    """Maps a batch of observations to a batch of actions."""

    def __call__(self, obs: torch.Tensor) -> torch.Tensor: ...

    def env_action(self, action: torch.Tensor) -> torch.Tensor:
        """What the env receives for `action`, while observers keep `action` itself. PPO's
        continuous samples, whose log-probabilities its ratio needs, reach the env clipped or
        squashed into the bounds. The default: the action as it is."""
        return action

    def state_dict(self) -> dict[str, Any]:
        """State of the policy's own that a checkpoint keeps (a noise generator on a GPU);
        the default: none."""
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore `state_dict()`; the default has nothing to restore."""
        return None


@runtime_checkable
class Observer(Protocol):
    """Sees every batched transition the actor produces (metrics, replay writers)."""

    def __call__(self, transition: Transition) -> None: ...

    def flush(self) -> None:
        """Hand on what is staged, at the end of every collect call, before anyone samples
        (replay writers). The default: nothing is staged."""
        return None


class CallablePolicy(Policy):
    """A plain function obs -> action as a Policy (its defaults: actions reach the env as they
    are, no state), for an Actor given a function, as TF-Agents' py_policy users write them."""

    def __init__(self, fn: Any) -> None:
        self.fn = fn

    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        return self.fn(obs)


def as_policy(policy: Any) -> Policy:
    """`policy` as a Policy: itself where it is one, a plain function wrapped (`CallablePolicy`).
    An object of another class is refused: one with an `env_action` of its own would lose it."""
    if isinstance(policy, Policy):
        return policy
    if not isinstance(policy, FUNCTIONS):
        raise TypeError(f"a policy is a relayrl.core.Policy (subclass it: its env_action, state_dict and "
                        f"load_state_dict have defaults) or a plain function obs -> action, not "
                        f"{type(policy).__name__}")
    return CallablePolicy(policy)


FUNCTIONS = (types.FunctionType, types.MethodType, types.BuiltinFunctionType, functools.partial)


class CallableObserver(Observer):
    """A plain function of a Transition as an Observer (nothing staged), as TF-Agents' observers."""

    def __init__(self, fn: Any) -> None:
        self.fn = fn

    def __call__(self, transition: Transition) -> None:
        self.fn(transition)


class Agent(Saveable, Protocol):
    """What the train loop knows of an algorithm. The factory that builds one returns this type."""

    # The env's spaces it was built for: what its checkpoints and policy files record.
    obs_spec: Spec
    action_spec: Spec
    # Training metrics that are NaN where they are undefined (PPO's explained variance when a
    # rollout's returns are all equal): logged as they are, not taken for a diverging run.
    undefined_metrics: frozenset[str] = frozenset()
    train_step: int  # gradient steps so far

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

    def train(self, batch: Any) -> dict[str, torch.Tensor]:
        """One update on a sampled `Batch` (or what `prepare` made of it), or, for an on-policy
        agent, on a rollout (a dict of [1, T, B, ...] tensors). Returns scalar metrics as
        tensors (no host sync forced)."""
        ...

    def policy_state(self) -> dict[str, Any]:
        """What `relayrl.load_policy` needs to rebuild the eval policy without the agent."""
        ...

    def scalars(self, env_steps: int) -> dict[str, float]:
        """Schedules' current values (epsilon, learning_rate), logged as TensorBoard's charts/<name>."""
        ...

    def set_progress(self, env_steps: int) -> None:
        """Follow schedules that run on env steps (learning rates, clip ranges), called after
        every collect. The default: no such schedule."""
        return None

    def prepare_horizon(self) -> int:
        """How many of the next train() calls a chunk prepared now stays valid for; 0 (the
        default): nothing is computed ahead. A local uniform learner then draws chunks of at
        most that many batches and hands each to `prepare` before slicing it into batches."""
        return 0

    def prepare(self, batch: Batch, steps: int) -> tuple[torch.Tensor | None, ...]:
        """The chunk of the next `steps` batches with what stays valid for all of them computed
        once (DQN: its target network's Q-values of the next observations), as a NamedTuple of
        [steps * N, ...] tensors that the learner slices row-wise. The default: `batch` itself."""
        return batch

    def device_collect_policy(self, network: nn.Module | None = None) -> Policy | None:
        """The collect policy for a stateless torch env, acting without leaving the env's device
        (`network` as for `collect_policy`). None (the default): `collect_policy` serves."""
        return None
