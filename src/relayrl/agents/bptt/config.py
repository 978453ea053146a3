"""Hyperparameters of training through a differentiable rollout (TorchRL's Pendulum tutorial):
the `agent` section of an `algo = "bptt"` config, and what `train_bptt` takes."""

from __future__ import annotations

from dataclasses import dataclass, field

from relayrl.config_fields import Section
from relayrl.errors import ConfigError


@dataclass
class BpttConfig(Section):
    SECTION = "agent"

    hidden: list[int] = field(default_factory=lambda: [64, 64, 64])  # Tanh MLP, linear output
    lr: float = 2e-3  # Adam learning rate
    lr_t_max: int = 20_000  # CosineAnnealingLR's T_max, stepped once per iteration (the tutorial's)
    max_grad_norm: float = 1.0  # gradients are clipped to this global norm
    batch_size: int = 32  # rollouts per iteration, from random initial states
    rollout_steps: int = 100  # env steps per rollout, back-propagated through
    fast: bool = True  # the hand-written backward for Pendulum + MLP (false: autograd through rollout())

    def validate(self) -> None:
        if not self.hidden or any(h < 1 for h in self.hidden):
            raise ConfigError(f"agent.hidden={self.hidden} is not valid; give one or more positive sizes")
        for key in ("lr", "max_grad_norm"):
            if getattr(self, key) <= 0:
                raise ConfigError(f"agent.{key}={getattr(self, key)} is not valid; it must be > 0")
        for key in ("lr_t_max", "batch_size", "rollout_steps"):
            if getattr(self, key) < 1:
                raise ConfigError(f"agent.{key}={getattr(self, key)} is not valid; it must be >= 1")
