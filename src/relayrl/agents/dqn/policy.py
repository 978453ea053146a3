"""A saved DQN policy (kind "q_greedy"): greedy in Q, for `load_policy` and `export_policy`."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import torch
from torch import nn

from relayrl.policies import GreedyPolicy, saved_network


def load(state: dict[str, Any], device: torch.device, deterministic: bool, seed: int | None) -> GreedyPolicy:
    return GreedyPolicy(saved_network(state, state["num_actions"]).to(device), device)


class ArgmaxQ(nn.Module):
    def __init__(self, state: dict[str, Any]) -> None:
        super().__init__()
        self.net = saved_network(state, state["num_actions"])

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.net(obs).argmax(dim=1)  # [B]


deterministic_module = ArgmaxQ  # the deterministic policy as a module, for export_policy


def action_space(state: dict[str, Any]) -> gym.Space:
    return gym.spaces.Discrete(int(state["num_actions"]))
