"""Hyperparameters of training through a differentiable rollout (TorchRL's Pendulum tutorial):
the `agent` section of an `algo = "bptt"` config, and what `train_bptt` takes."""

from __future__ import annotations

from dataclasses import dataclass, field

from relayrl.config_fields import Section


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
        self.require_sizes("hidden")
        self.require("> 0", "lr", "max_grad_norm")
        self.require(">= 1", "lr_t_max", "batch_size", "rollout_steps")
