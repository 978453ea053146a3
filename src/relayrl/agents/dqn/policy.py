"""A saved DQN policy (kind "q_greedy"): greedy in Q, for `load_policy` and `export_policy`."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import torch
from torch import nn

from relayrl.agents.dqn.networks import conv_state_dict
from relayrl.policies import GreedyPolicy, saved_network


def q_net(state: dict[str, Any]) -> nn.Module:
    """The saved Q-network. A file with `"network"` (a conv Q-network, "obs_shape" and keys
    convs.*, head.0.*, head.2.*) is read as the Nature CNN encoder with its linear head."""
    if state.get("network", "mlp") != "mlp":
        space = state.get("obs_space", {"kind": "box", "shape": state["obs_shape"], "dtype": "uint8"})
        state = {**state, "obs_space": space, "encoder": "nature_cnn", "obs_dim": 512, "hidden": [],
                 "activation": "relu", "state_dict": conv_state_dict(state["state_dict"])}
    return saved_network(state, state["num_actions"])


def load(state: dict[str, Any], device: torch.device, deterministic: bool, seed: int | None) -> GreedyPolicy:
    return GreedyPolicy(q_net(state).to(device), device)


class ArgmaxQ(nn.Module):
    def __init__(self, state: dict[str, Any]) -> None:
        super().__init__()
        self.net = q_net(state)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.net(obs).argmax(dim=1)  # [B]


deterministic_module = ArgmaxQ  # the deterministic policy as a module, for export_policy


def action_space(state: dict[str, Any]) -> gym.Space:
    return gym.spaces.Discrete(int(state["num_actions"]))
