"""Generalised advantage estimation (Schulman et al. 2016) over a rollout of [T, B] steps."""

from __future__ import annotations

import torch


@torch.no_grad()
def gae(rewards: torch.Tensor, values: torch.Tensor, next_values: torch.Tensor, terminated: torch.Tensor,
        truncated: torch.Tensor, gamma: float, lam: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Advantages and returns (advantages + values), each [T, B].

    `values[t]` is V(obs_t), `next_values[t]` V(next_obs_t): the value of the true next
    observation, also where a time limit cut the episode, so truncation bootstraps and
    termination does not. The lambda-sum stops at every episode end (either kind); the
    rollout's last step bootstraps from V of the observation the next rollout starts from.
    """
    not_term = (~terminated.bool()).to(values.dtype)
    not_done = (~(terminated.bool() | truncated.bool())).to(values.dtype)
    deltas = rewards + gamma * not_term * next_values - values
    adv = torch.zeros_like(values)
    running = torch.zeros_like(values[0])
    for t in range(rewards.shape[0] - 1, -1, -1):
        running = deltas[t] + gamma * lam * not_done[t] * running
        adv[t] = running
    return adv, adv + values
