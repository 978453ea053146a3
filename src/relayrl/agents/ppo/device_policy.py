"""PPO's collect policy (`policy.PPOCollectPolicy`'s distribution and `env_action`) in torch ops
on the observations' device, for stateless torch envs: actions stay tensors there and the noise
comes from a torch Generator on that device (checkpointed through `state_dict`), so env, policy
and rollout never go through the host. On CUDA the forward pass and the draw replay from one
CUDA graph per batch size (`nn.graphed`; the generator registered with it)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import nn

from relayrl.agents.ppo.distributions import EnvBounds
from relayrl.core import Policy
from relayrl.nn.graphed import GraphedStep, cuda_graphs_enabled
from relayrl.seeding import restore_generator


class PPODevicePolicy(Policy):
    def __init__(self, net: nn.Module, log_std: torch.Tensor | None, bounds: tuple[np.ndarray, np.ndarray] | None,
                 device: torch.device, seed: int, squash: str = "clip") -> None:
        self.net = net  # obs -> logits or mean [B, A]
        self.log_std = log_std  # [A]; None for discrete actions (pulls update it in place)
        self.device = device
        self.to_env = EnvBounds(bounds, squash, device)
        self.gen = torch.Generator(device=device)
        self.gen.manual_seed(seed)
        self._graphed = GraphedStep(self._act, generators=[self.gen]) if cuda_graphs_enabled(device) else None

    @torch.no_grad()
    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        """Discrete: the action [B]. Continuous: the Gaussian sample u [B, A], unbounded."""
        obs = obs.to(self.device)
        if self._graphed is None:
            return self._act(obs)["action"]
        return self._graphed(obs)["action"].clone()  # the graph's buffer is overwritten by the next call

    def _act(self, obs: torch.Tensor) -> dict[str, torch.Tensor]:
        out = self.net(obs).float()  # [B, A]
        if self.log_std is None:
            u = torch.rand((out.shape[0], 1), generator=self.gen, device=self.device, dtype=torch.float64)
            probs = torch.softmax(out.double(), dim=1)
            return {"action": (probs.cumsum(dim=1) < u).sum(dim=1).clamp_(max=out.shape[1] - 1)}  # [B]
        noise = torch.randn(out.shape, generator=self.gen, device=self.device)
        return {"action": out + self.log_std.detach().float().exp() * noise}

    def env_action(self, action: torch.Tensor) -> torch.Tensor:
        """What the env receives for `action`: clipped or squashed into the bounds."""
        return self.to_env(action)

    def state_dict(self) -> dict[str, Any]:
        return {"gen": self.gen.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if "gen" in state:
            restore_generator(self.gen, state["gen"])  # saved on a GPU, resumed on a CPU too
