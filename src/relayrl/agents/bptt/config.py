"""Hyperparameters of training through a differentiable rollout (TorchRL's Pendulum tutorial):
the `agent` section of an `algo = "bptt"` config, and what `train_bptt` takes."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from relayrl.config_fields import Section

ENV_ID = "relayrl/StatelessPendulum-v0"


@dataclass
class BpttConfig(Section):
    SECTION = "agent"
    # A run trains through this env only, and reads these keys of [env], [train], [eval] and
    # [distributed]; the others set the actor-learner loop it does not run, so `Config.validate`
    # refuses a value other than the default rather than ignore it (the reason: WHY_UNUSED, or UNUSED).
    ENV_IDS: ClassVar[tuple[str, ...]] = (ENV_ID,)
    RUN_KEYS: ClassVar[tuple[str, ...]] = ("env.id", "train.total_steps", "train.torch_threads", "eval.interval",
                                           "eval.episodes")
    WHY_UNUSED: ClassVar[dict[str, str]] = {
        "env.num_envs": "each iteration rolls out agent.batch_size pendulums as one batch (set agent.batch_size)",
        "distributed.num_actors": "it runs in one process only",
    }
    UNUSED: ClassVar[str] = (f"it trains and evaluates through {ENV_ID} as it is, without the env copies, "
                             "collection, checkpoints and Ray actors this key sets")

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

    def iteration_steps(self) -> int:
        """Env steps one iteration takes: batch_size rollouts of rollout_steps."""
        return self.batch_size * self.rollout_steps
