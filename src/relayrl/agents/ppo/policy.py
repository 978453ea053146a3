"""PPO's acting policy, and its saved policy (kind "ppo") for `load_policy` and `export_policy`.

Discrete actions: a categorical over the actor's logits, argmax when deterministic.
Continuous: a Gaussian around the actor's mean with a state-independent std, the mean when
deterministic; either clipped to the action bounds. Noise comes from a NumPy generator
(the agent's, checkpointed with it); actions are CPU tensors.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import nn

from relayrl.policies import saved_bounds, saved_network


class PPOPolicy:
    env_steps: int | None = None  # when a loaded policy was saved (see relayrl.load_policy)

    def __init__(self, net: nn.Module, log_std: torch.Tensor | None, bounds: tuple[np.ndarray, np.ndarray] | None,
                 device: torch.device, deterministic: bool, rng: np.random.Generator | None = None) -> None:
        self.net = net  # obs -> logits or mean [B, A]
        self.log_std = log_std  # [A]; None for discrete actions (read at each call: pulls update it in place)
        self.device = device
        self.deterministic = deterministic
        self.rng = rng if rng is not None else np.random.default_rng()
        self.low = self.high = None
        if bounds is not None:
            self.low, self.high = (torch.as_tensor(b, dtype=torch.float32) for b in bounds)

    @torch.no_grad()
    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        out = self.net(obs.to(self.device, non_blocking=True)).float().cpu()  # [B, A]
        if self.log_std is None:
            if self.deterministic:
                return out.argmax(dim=1)
            probs = torch.softmax(out.double(), dim=1)
            u = torch.from_numpy(self.rng.random((out.shape[0], 1)))
            return (probs.cumsum(dim=1) < u).sum(dim=1).clamp_(max=out.shape[1] - 1)  # inverse CDF [B]
        a = out
        if not self.deterministic:
            noise = torch.from_numpy(self.rng.standard_normal(out.shape, dtype=np.float32))
            a = out + self.log_std.detach().float().cpu().exp() * noise
        return torch.minimum(torch.maximum(a, self.low), self.high)


def load(state: dict[str, Any], device: torch.device, deterministic: bool, seed: int | None) -> PPOPolicy:
    net = saved_network(state, state["action_dim"]).to(device)
    if state["discrete"]:
        return PPOPolicy(net, None, None, device, deterministic, np.random.default_rng(seed))
    log_std = torch.as_tensor(state["log_std"], dtype=torch.float32)
    return PPOPolicy(net, log_std, saved_bounds(state), device, deterministic, np.random.default_rng(seed))


class Greedy(nn.Module):
    """argmax of the logits, or the mean clipped to the bounds: the deterministic action."""

    def __init__(self, state: dict[str, Any]) -> None:
        super().__init__()
        self.net = saved_network(state, state["action_dim"])
        self.discrete = bool(state["discrete"])
        if not self.discrete:
            low, high = saved_bounds(state)
            self.register_buffer("low", torch.as_tensor(low, dtype=torch.float32))
            self.register_buffer("high", torch.as_tensor(high, dtype=torch.float32))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        out = self.net(obs)
        if self.discrete:
            return out.argmax(dim=1)  # [B]
        return torch.minimum(torch.maximum(out, self.low), self.high)  # [B, A]


def deterministic_module(state: dict[str, Any]) -> nn.Module:
    return Greedy(state)
