"""PPO's acting policies, and its saved policy (kind "ppo") for `load_policy` and `export_policy`.

Discrete actions: a categorical over the actor's logits, argmax when deterministic.
Continuous: a Gaussian sample u around the actor's mean with a state-independent std, u = the
mean when deterministic; the env receives u clipped to the action bounds, or squashed into them
(loc + scale * tanh(u), `agent.squash = "tanh"`). `PPOPolicy` returns what the env receives;
`PPOCollectPolicy` returns u itself, which the rollout keeps, and maps it with `env_action`
where the Actor steps the env. Noise comes from a NumPy generator (the agent's, checkpointed
with it); actions are CPU tensors. A policy saved with observation normalisation normalises
its observations with the statistics it was saved with.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import nn

from relayrl.agents.ppo.distributions import squash
from relayrl.agents.ppo.normalize import ObsNorm
from relayrl.policies import saved_bounds, saved_network

SQUASHES = ("clip", "tanh")


class PPOPolicy:
    env_steps: int | None = None  # when a loaded policy was saved (see relayrl.load_policy)

    def __init__(self, net: nn.Module, log_std: torch.Tensor | None, bounds: tuple[np.ndarray, np.ndarray] | None,
                 device: torch.device, deterministic: bool, rng: np.random.Generator | None = None,
                 squash: str = "clip") -> None:
        self.net = net  # obs -> logits or mean [B, A]
        self.log_std = log_std  # [A]; None for discrete actions (read at each call: pulls update it in place)
        self.device = device
        self.deterministic = deterministic
        self.rng = rng if rng is not None else np.random.default_rng()
        self.squash = squash
        self.low = self.high = None
        if bounds is not None:
            self.low, self.high = (torch.as_tensor(b, dtype=torch.float32) for b in bounds)
            self.loc, self.scale = (self.high + self.low) / 2, (self.high - self.low) / 2

    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        return self.bound(self.sample(obs))

    @torch.no_grad()
    def sample(self, obs: torch.Tensor) -> torch.Tensor:
        """Discrete: the action [B]. Continuous: the Gaussian sample u [B, A] (the mean when
        deterministic), before clipping or squashing."""
        out = self.net(obs.to(self.device, non_blocking=True)).float().cpu()  # [B, A]
        if self.log_std is None:
            if self.deterministic:
                return out.argmax(dim=1)
            probs = torch.softmax(out.double(), dim=1)
            u = torch.from_numpy(self.rng.random((out.shape[0], 1)))
            return (probs.cumsum(dim=1) < u).sum(dim=1).clamp_(max=out.shape[1] - 1)  # inverse CDF [B]
        if self.deterministic:
            return out
        noise = torch.from_numpy(self.rng.standard_normal(out.shape, dtype=np.float32))
        return out + self.log_std.detach().float().cpu().exp() * noise

    def bound(self, u: torch.Tensor) -> torch.Tensor:
        """The action the env receives for `sample`'s u: clipped or squashed into the bounds."""
        if self.low is None:
            return u
        if self.squash == "tanh":
            return squash(u, self.loc, self.scale)
        return torch.minimum(torch.maximum(u, self.low), self.high)


class PPOCollectPolicy(PPOPolicy):
    """The exploring policy of a run: its actions are the samples u (see `PPOPolicy.sample`),
    which the rollout stores; the Actor steps the env with `env_action(u)`."""

    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        return self.sample(obs)

    def env_action(self, action: torch.Tensor) -> torch.Tensor:
        return self.bound(action)


def saved_policy_network(state: dict[str, Any]) -> nn.Module:
    """The saved actor MLP, behind the saved observation normaliser when the run had one."""
    net = saved_network(state, state["action_dim"])
    if state.get("obs_mean") is None:
        return net
    return nn.Sequential(ObsNorm.from_saved(state), net).eval()


def load(state: dict[str, Any], device: torch.device, deterministic: bool, seed: int | None) -> PPOPolicy:
    net = saved_policy_network(state).to(device)
    if state["discrete"]:
        return PPOPolicy(net, None, None, device, deterministic, np.random.default_rng(seed))
    log_std = torch.as_tensor(state["log_std"], dtype=torch.float32)
    return PPOPolicy(net, log_std, saved_bounds(state), device, deterministic, np.random.default_rng(seed),
                     squash=state.get("squash", "clip"))


class Greedy(nn.Module):
    """argmax of the logits, or the mean clipped or squashed into the bounds: the deterministic action."""

    def __init__(self, state: dict[str, Any]) -> None:
        super().__init__()
        self.net = saved_policy_network(state)
        self.discrete = bool(state["discrete"])
        self.tanh = state.get("squash", "clip") == "tanh"
        if not self.discrete:
            low, high = (torch.as_tensor(b, dtype=torch.float32) for b in saved_bounds(state))
            self.register_buffer("low", low)
            self.register_buffer("high", high)
            self.register_buffer("loc", (high + low) / 2)
            self.register_buffer("scale", (high - low) / 2)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        out = self.net(obs)
        if self.discrete:
            return out.argmax(dim=1)  # [B]
        if self.tanh:
            return squash(out, self.loc, self.scale)  # [B, A]
        return torch.minimum(torch.maximum(out, self.low), self.high)  # [B, A]


def deterministic_module(state: dict[str, Any]) -> nn.Module:
    return Greedy(state)
