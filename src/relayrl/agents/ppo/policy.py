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

from relayrl.nn import MLP
from relayrl.nn.mlp_fast import MLPInference
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
        # A float32 MLP on the CPU (the run's PolicyNet holds one as `mlp`, a saved policy is
        # one) runs through MLPInference: NumPy views of its weights for small batches.
        mlp = getattr(net, "mlp", net)
        self.outputs = getattr(net, "out", None)  # a shared net's MLP has the value as one more output
        self._cpu = (MLPInference(mlp) if isinstance(mlp, MLP) and device.type == "cpu"
                     and all(p.dtype == torch.float32 for p in mlp.parameters()) else None)
        if bounds is not None:
            self.low, self.high = (torch.as_tensor(b, dtype=torch.float32) for b in bounds)

    def _outputs(self, obs: torch.Tensor) -> np.ndarray:
        """The network's outputs [B, A] (logits or Gaussian mean) as a float32 NumPy array."""
        if self._cpu is not None and obs.device.type == "cpu":
            return self._cpu(obs)[:, : self.outputs]
        with torch.no_grad():
            return self.net(obs.to(self.device, non_blocking=True)).float().cpu().numpy()

    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        out_np = self._outputs(obs)  # [B, A]
        if self.log_std is None:
            if self.deterministic:
                return torch.from_numpy(out_np.argmax(axis=1))
            logits = out_np.astype(np.float64)
            e = np.exp(logits - logits.max(axis=1, keepdims=True))
            cdf = np.cumsum(e / e.sum(axis=1, keepdims=True), axis=1)
            u = self.rng.random((out_np.shape[0], 1))
            return torch.from_numpy(np.minimum((cdf < u).sum(axis=1), out_np.shape[1] - 1))  # inverse CDF [B]
        out = torch.from_numpy(out_np)
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
