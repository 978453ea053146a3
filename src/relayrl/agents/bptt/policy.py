"""A saved BPTT policy (kind "clamped_mlp"): the MLP's output clamped to the action bounds, as
the env clamps it, for `load_policy` and `export_policy`."""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from relayrl.policies import ClampedPolicy, box_action_space, saved_bounds, saved_network


def load(state: dict[str, Any], device: torch.device, deterministic: bool, seed: int | None) -> ClampedPolicy:
    net = saved_network(state, state["action_dim"]).to(device)
    return ClampedPolicy(net, *saved_bounds(state), device)


class Clamped(nn.Module):
    low: torch.Tensor  # buffers
    high: torch.Tensor

    def __init__(self, state: dict[str, Any]) -> None:
        super().__init__()
        self.net = saved_network(state, state["action_dim"])
        low, high = saved_bounds(state)
        self.register_buffer("low", torch.as_tensor(low, dtype=torch.float32))
        self.register_buffer("high", torch.as_tensor(high, dtype=torch.float32))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.minimum(torch.maximum(self.net(obs), self.low), self.high)  # [B, A]


deterministic_module = Clamped  # the deterministic policy as a module, for export_policy


action_space = box_action_space  # the env's Box, from the file (a saved policy's `action_space`)
