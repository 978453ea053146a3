"""`rollout`: run a policy through a stateless env for T steps, keeping the autograd graph.

Nothing here detaches, uses `no_grad` or writes in place into tensors the graph holds, so a
loss on the returned rewards backpropagates through the dynamics into the policy's weights
and the initial state (the TorchRL Pendulum tutorial's training, `agents/bptt/bptt.py`). Results are
stacked with a leading time dim: `[T, *B, ...]`.

The rollout does not reset finished episodes: done flags are reported and stepping goes on
(Pendulum only truncates, so the dynamics stay valid). Use `StatelessBatchEnv` (adapter.py)
for auto-resetting batched stepping.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import torch

from relayrl.envs.stateless.base import Obs, StatelessEnv


class Rollout(NamedTuple):
    obs: Obs  # name -> [T, *B, ...]: the observation each action was taken from
    action: torch.Tensor  # [T, *B, *act_shape]
    reward: torch.Tensor  # [T, *B]
    terminated: torch.Tensor  # [T, *B] bool
    truncated: torch.Tensor  # [T, *B] bool
    final_obs: Obs  # name -> [*B, ...]: the observation after the last step
    state: Any  # the state after the last step

    def next_obs(self) -> Obs:
        """name -> [T, *B, ...]: the observation after each action."""
        return {k: torch.cat([v[1:], self.final_obs[k].unsqueeze(0)]) for k, v in self.obs.items()}


def rollout(env: StatelessEnv, policy: Callable[[Any], torch.Tensor], steps: int, state: Any,
            obs_key: str | None = "observation") -> Rollout:
    """Step `env` `steps` times from `state`, acting with `policy`.

    `policy` gets `obs[obs_key]` (a tensor `[*B, obs_dim]`), or the whole observation dict
    when `obs_key` is None, and returns actions `[*B, *action_spec.shape]`.
    """
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    obs = env.observe(state)
    seen: list[Obs] = []
    actions, rewards, terms, truncs = [], [], [], []
    for _ in range(steps):
        action = policy(obs if obs_key is None else obs[obs_key])
        out = env.step(state, action)
        seen.append(obs)
        actions.append(action)
        rewards.append(out.reward)
        terms.append(out.terminated)
        truncs.append(out.truncated)
        state, obs = out.state, out.obs
    stacked = {k: torch.stack([o[k] for o in seen]) for k in seen[0]}
    return Rollout(stacked, torch.stack(actions), torch.stack(rewards), torch.stack(terms),
                   torch.stack(truncs), obs, state)
