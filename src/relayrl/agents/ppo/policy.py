"""PPO's acting policies, and its saved policy (kind "ppo") for `load_policy` and `export_policy`.

The distributions are those of distributions.py, at their mode when deterministic. `PPOPolicy`
returns what the env receives; `PPOCollectPolicy` returns the Gaussian sample u itself, which the
rollout keeps, and maps it with `env_action` where the Actor steps the env. Noise comes from a
NumPy generator (the agent's, checkpointed with it); actions are CPU tensors. A policy saved with
observation normalisation normalises its observations with the statistics it was saved with.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from relayrl.agents.ppo.distributions import EnvBounds, greedy_logits_action, to_bounds
from relayrl.agents.ppo.networks import ActionHead, PolicyNet, action_head
from relayrl.agents.ppo.normalize import ObsNorm
from relayrl.core import Policy
from relayrl.policies import box_action_space, cpu_mlp, saved_bounds, saved_network
from relayrl.specs import spec_from_state, to_space


class PPOPolicy(Policy):
    def __init__(self, net: nn.Module, log_std: torch.Tensor | None, bounds: tuple[np.ndarray, np.ndarray] | None,
                 device: torch.device, deterministic: bool, rng: np.random.Generator | None = None,
                 squash: str = "clip", head: ActionHead | None = None) -> None:
        self.net = net  # obs -> logits or mean [B, A]
        self.head = head if head is not None else ActionHead(0, log_std is None)
        self.log_std = log_std  # [A]; None for discrete actions (read at each call: pulls update it in place)
        self.device = device
        self.deterministic = deterministic
        self.rng = rng if rng is not None else np.random.default_rng()
        self.to_env = EnvBounds(bounds, squash)  # `sample`'s u -> the action the env receives
        # A float32 MLP on the CPU (the run's PolicyNet holds one as `mlp`, a saved policy is
        # one) runs through MLPInference: NumPy views of its weights for small batches; not
        # behind an observation normaliser or an encoder, which only the torch forward applies.
        self.outputs: int | None = None  # a shared net's MLP has the value as one more output
        mlp, plain = net, True
        if isinstance(net, PolicyNet):
            mlp, self.outputs, plain = net.mlp, net.out, net.obs_norm is None and net.encoder is None
        self._cpu = cpu_mlp(mlp, device) if plain else None

    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        return self.to_env(self.sample(obs))

    def _outputs(self, obs: torch.Tensor) -> np.ndarray:
        """The network's outputs [B, A] (logits or Gaussian mean) as a float32 NumPy array."""
        if self._cpu is not None and obs.device.type == "cpu":
            return self._cpu(obs)[:, : self.outputs]
        with torch.no_grad():
            return self.net(obs.to(self.device, non_blocking=True)).float().cpu().numpy()

    def sample(self, obs: torch.Tensor) -> torch.Tensor:
        """Discrete: the action [B]. Continuous: the Gaussian sample u [B, A] (the mean when
        deterministic), before clipping or squashing."""
        out_np = self._outputs(obs)  # [B, A]
        h = self.head
        if h.binary or h.nvec:  # a MultiDiscrete of one entry too: its actions have the space's shape [B, 1]
            return self._sample_multi(out_np).reshape(out_np.shape[0], *h.shape)
        if self.log_std is None:
            if self.deterministic:
                return torch.from_numpy(out_np.argmax(axis=1))
            return torch.from_numpy(self._categorical(out_np))
        out = torch.from_numpy(out_np)
        if self.deterministic:
            return out
        noise = torch.from_numpy(self.rng.standard_normal(out.shape, dtype=np.float32))
        return out + self.log_std.detach().float().cpu().exp() * noise

    def _categorical(self, logits: np.ndarray) -> np.ndarray:
        """One draw per row of a categorical over `logits` [B, n]: the inverse CDF of a uniform."""
        x = logits.astype(np.float64)
        e = np.exp(x - x.max(axis=1, keepdims=True))
        cdf = np.cumsum(e / e.sum(axis=1, keepdims=True), axis=1)
        u = self.rng.random((x.shape[0], 1))
        return np.minimum((cdf < u).sum(axis=1), x.shape[1] - 1)  # [B]

    def _sample_multi(self, out: np.ndarray) -> torch.Tensor:
        """MultiBinary [B, A] int8 or MultiDiscrete [B, k] int64 actions from their logits."""
        h = self.head
        if self.deterministic:
            return greedy_logits_action(torch.from_numpy(out), h.nvec, h.binary)
        if h.binary:
            return torch.from_numpy((self.rng.random(out.shape) * (1.0 + np.exp(-out)) < 1.0).astype(np.int8))
        blocks = np.split(out, np.cumsum(h.nvec)[:-1], axis=1)
        return torch.from_numpy(np.stack([self._categorical(b) for b in blocks], axis=1))


class PPOCollectPolicy(PPOPolicy):
    """The exploring policy of a run: its actions are the samples u (see `PPOPolicy.sample`),
    which the rollout stores; the Actor steps the env with `env_action(u)`."""

    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        return self.sample(obs)

    def env_action(self, action: torch.Tensor) -> torch.Tensor:
        return self.to_env(action)


def saved_policy_network(state: dict[str, Any]) -> nn.Module:
    """The saved actor MLP, behind the saved observation normaliser when the run had one."""
    net = saved_network(state, state["action_dim"])
    if state.get("obs_mean") is None:
        return net
    return nn.Sequential(ObsNorm.from_saved(state), net).eval()


def saved_head(state: dict[str, Any]) -> ActionHead:
    """The action head a saved policy's outputs parameterise (files before MultiDiscrete and
    MultiBinary actions hold one categorical or a Gaussian)."""
    if "action_space" in state and state["action_space"]["kind"] != "box":  # (the file keeps a Box's bounds apart)
        return action_head(spec_from_state(state["action_space"]))
    return ActionHead(int(state["action_dim"]), bool(state["discrete"]))


def load(state: dict[str, Any], device: torch.device, deterministic: bool, seed: int | None) -> PPOPolicy:
    net = saved_policy_network(state).to(device)
    if state["discrete"]:
        return PPOPolicy(net, None, None, device, deterministic, np.random.default_rng(seed), head=saved_head(state))
    log_std = torch.as_tensor(state["log_std"], dtype=torch.float32)
    return PPOPolicy(net, log_std, saved_bounds(state), device, deterministic, np.random.default_rng(seed),
                     squash=state.get("squash", "clip"))


class Greedy(nn.Module):
    """argmax of the logits, or the mean clipped or squashed into the bounds: the deterministic action."""

    low: torch.Tensor  # buffers of a continuous policy, declared for the type checker
    high: torch.Tensor

    def __init__(self, state: dict[str, Any]) -> None:
        super().__init__()
        self.net = saved_policy_network(state)
        self.discrete = bool(state["discrete"])
        h = saved_head(state)
        self.nvec, self.binary, self.shape = h.nvec, h.binary, h.shape
        self.tanh = state.get("squash", "clip") == "tanh"
        if not self.discrete:
            low, high = (torch.as_tensor(b, dtype=torch.float32) for b in saved_bounds(state))
            self.register_buffer("low", low)
            self.register_buffer("high", high)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        out = self.net(obs)
        if self.discrete:
            a = greedy_logits_action(out, self.nvec, self.binary)  # [B] or [B, k]
            return a.reshape(a.shape[0], *self.shape) if self.shape else a
        return to_bounds(out, self.low, self.high, self.tanh)  # [B, A]


deterministic_module = Greedy  # the deterministic policy as a module, for export_policy


def action_space(state: dict[str, Any]) -> gym.Space:
    """The env's action space, from the file: a Box from its bounds (`box_action_space`); else
    the space it records (files before MultiDiscrete and MultiBinary actions: Discrete)."""
    if not state["discrete"]:
        return box_action_space(state)
    if "action_space" in state:
        return to_space(spec_from_state(state["action_space"]))
    return gym.spaces.Discrete(int(state["action_dim"]))
