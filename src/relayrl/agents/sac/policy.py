"""A saved SAC policy (kind "tanh_gaussian"): tanh(mean), or sampled, for `load_policy`; the
deterministic one for `export_policy`."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import nn

from relayrl.policies import TanhGaussianPolicy, box_action_space, saved_bounds, saved_network


def load(state: dict[str, Any], device: torch.device, deterministic: bool, seed: int | None) -> TanhGaussianPolicy:
    net = saved_network(state, 2 * state["action_dim"]).to(device)
    return TanhGaussianPolicy(net, *saved_bounds(state), device,
                              deterministic, np.random.default_rng(seed), state["log_std_min"], state["log_std_max"])


class TanhMean(nn.Module):
    """loc + scale * tanh(mean): the action at the Gaussian's mean."""

    loc: torch.Tensor  # buffers
    scale: torch.Tensor
    low: torch.Tensor
    high: torch.Tensor

    def __init__(self, state: dict[str, Any]) -> None:
        super().__init__()
        self.net = saved_network(state, 2 * state["action_dim"])
        low, high = saved_bounds(state)
        self.register_buffer("loc", torch.as_tensor((high + low) / 2.0, dtype=torch.float32))
        self.register_buffer("scale", torch.as_tensor((high - low) / 2.0, dtype=torch.float32))
        # clamped as TanhGaussianPolicy's actions are: loc +- scale can round a step past a bound
        self.register_buffer("low", torch.as_tensor(low, dtype=torch.float32))
        self.register_buffer("high", torch.as_tensor(high, dtype=torch.float32))
        self.action_dim = int(state["action_dim"])

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        a = self.loc + self.scale * torch.tanh(self.net(obs)[:, : self.action_dim])  # [B, A]
        return torch.minimum(torch.maximum(a, self.low), self.high)


deterministic_module = TanhMean  # the deterministic policy as a module, for export_policy


action_space = box_action_space  # the env's Box, from the file (a saved policy's `action_space`)
