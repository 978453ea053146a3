"""SAC hyperparameters (Haarnoja et al. 2018, with automatic entropy tuning)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from relayrl.config_fields import ACTIVATION_NAMES, Section
from relayrl.errors import ConfigError


@dataclass
class SACConfig(Section):
    SECTION = "agent"
    NETWORK = ("actor_hidden", "critic_hidden", "activation", "encoder")
    SCHEDULES = (("actor_lr", "lr_end"), ("critic_lr", "lr_end"), ("alpha_lr", "lr_end"))

    actor_hidden: list[int] = field(default_factory=lambda: [256, 256])  # hidden layer sizes of the actor MLP
    critic_hidden: list[int] = field(default_factory=lambda: [256, 256])  # hidden layer sizes of each critic MLP
    activation: str = "relu"  # relu | tanh | elu | leaky_relu | silu | gelu
    # observation encoder: auto (one-hot for Discrete / MultiDiscrete, a conv net for uint8 images 0..255,
    # each entry of a Dict / Tuple as that, flattened otherwise) | flatten | nature_cnn | small_cnn (float images too) |
    # package.module:make (your own: make(observation_space) returns a torch module, batch -> [B, features])
    encoder: str = "auto"
    actor_lr: float = 3e-4  # Adam learning rate of the actor
    critic_lr: float = 3e-4  # Adam learning rate of the critics
    alpha_lr: float = 3e-4  # Adam learning rate of the entropy temperature
    # < 0: constant learning rates; else actor_lr, critic_lr and alpha_lr each linear in env steps
    # to lr_end at train.total_steps (SB3 applies its one lr schedule to all three optimizers)
    lr_end: float = -1.0
    batch_size: int = 256  # transitions per gradient step
    gamma: float = 0.99  # discount factor
    tau: float = 0.005  # Polyak factor for the target critics
    target_update_period: int = 1  # gradient steps between target updates
    reward_scale: float = 1.0  # rewards are multiplied by this in the critic's target
    init_alpha: float = 1.0  # initial entropy temperature
    autotune_alpha: bool = True  # false: alpha stays init_alpha
    target_entropy: float | None = None  # None: -|A| (the SAC paper's heuristic)
    grad_clip: float = 0.0  # max global grad norm per network; 0 disables
    log_std_min: float = -20.0  # lower clip of the actor's log standard deviation
    log_std_max: float = 2.0  # upper clip of the actor's log standard deviation

    def over_total_steps(self) -> list[str]:
        return [f"agent.lr_end={self.lr_end}"] * (self.lr_end >= 0)

    def validate(self) -> None:
        self.require_encoder(self.encoder)
        self.require_choice(activation=ACTIVATION_NAMES)
        self.require_sizes("actor_hidden", "critic_hidden")
        self.require("> 0", "actor_lr", "critic_lr", "alpha_lr", "init_alpha", "reward_scale")
        self.require("in (0, 1]", "tau")
        self.require("in [0, 1]", "gamma")
        self.require(">= 1", "target_update_period", "batch_size")
        self.require(">= 0", "grad_clip", note=" (0: no clipping)")
        if self.log_std_min >= self.log_std_max:
            raise ConfigError(f"agent.log_std_min={self.log_std_min} is not valid; it must be below "
                              f"agent.log_std_max={self.log_std_max}")


# `relayrl train sac` / `algo = "sac"`: beyond the classes' defaults (the agent section above is
# SB3's SAC: 256x256, lr 3e-4, batch 256, tau 0.005, gamma 0.99, alpha auto), SB3's
# learning_starts 100 and 1M replay; 1 env step then 1 gradient step (SB3's train_freq 1,
# gradient_steps 1) are the train section's own defaults. One torch thread (train.torch_threads):
# SB3 takes every core, which on a shared machine is many times slower (issue 32).
DEFAULTS: dict[str, Any] = {
    "env": {"id": "Pendulum-v1"},  # the classes' CartPole-v1 has discrete actions, which SAC does not take
    "train": {"initial_collect_steps": 100},
    "replay": {"size": 1_000_000},
}
