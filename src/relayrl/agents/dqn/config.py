"""DQN hyperparameters (Double DQN is a flag)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from relayrl.config_fields import ACTIVATION_NAMES, Section
from relayrl.errors import ConfigError


@dataclass
class DQNConfig(Section):
    SECTION = "agent"
    NETWORK = ("hidden", "activation", "encoder", "network")
    SCHEDULES = (("lr", "lr_end"), ("epsilon_start", "epsilon_end"))

    hidden: list[int] = field(default_factory=lambda: [256, 256])  # Q-network MLP hidden sizes; []: linear
    activation: str = "relu"  # relu | tanh | elu | leaky_relu | silu | gelu
    # observation encoder: auto (one-hot for Discrete / MultiDiscrete, a conv net for uint8 images 0..255,
    # each entry of a Dict / Tuple as that, flattened otherwise) | flatten | nature_cnn | small_cnn (float images too) |
    # package.module:make (your own: make(observation_space) returns a torch module, batch -> [B, features])
    encoder: str = "auto"
    init: str = "torch"  # torch | tf-agents (VarianceScaling hidden, small uniform head, bias -0.2)
    # mlp: hidden/activation/init above | nature_cnn: Mnih et al. 2015's conv net for uint8
    # [k, H, W] frame stacks | mario_cnn: the Mario tutorial's net (the same layers)
    network: str = "mlp"
    lr: float = 1e-3  # Adam learning rate
    lr_end: float = -1.0  # < 0: constant lr; else linear decay to lr_end over train.total_steps
    adam_eps: float = 1e-8  # Adam's epsilon
    batch_size: int = 64  # transitions per gradient step
    gamma: float = 0.99  # discount factor
    loss: str = "huber"  # huber | mse (element-wise squared error, no 1/2)
    huber_delta: float = 1.0  # huber: where the loss turns from quadratic to linear
    double: bool = False  # Double DQN: the online net picks the next action, the target net values it
    target_update_period: int = 1  # gradient steps between target updates
    tau: float = 1.0  # 1.0: hard copy; < 1: Polyak averaging
    grad_clip: float = 0.0  # max global grad norm; 0 (or less) disables
    epsilon_start: float = 1.0  # exploration: random-action probability at the start
    epsilon_end: float = 0.05  # exploration: random-action probability at the end of the decay
    # env steps for the linear decay; 0: constant epsilon_end; -1: a tenth of train.total_steps
    epsilon_decay_steps: int = 10_000
    # linear: start -> end over epsilon_decay_steps | exponential: start * epsilon_decay ** t,
    # floored at epsilon_end (the Mario tutorial: 0.99999975 per env step, down to 0.1)
    epsilon_schedule: str = "linear"
    epsilon_decay: float = 0.99999975  # exponential: the factor per env step

    def unused(self) -> list[str]:
        return ["huber_delta"] * (self.loss != "huber") + ["epsilon_decay"] * (self.epsilon_schedule != "exponential")

    def over_total_steps(self) -> list[str]:
        tenth = self.epsilon_schedule == "linear" and self.epsilon_decay_steps == -1
        return [f"agent.lr_end={self.lr_end}"] * (self.lr_end >= 0) + ["agent.epsilon_decay_steps=-1"] * tenth

    def validate(self) -> None:
        self.require_encoder(self.encoder)
        self.require_choice(activation=ACTIVATION_NAMES, init=("torch", "tf-agents"),
                            loss=("huber", "mse"), network=("mlp", "nature_cnn", "mario_cnn"),
                            epsilon_schedule=("linear", "exponential"))
        if self.network != "mlp" and self.encoder not in ("auto", "nature_cnn"):
            # the conv net is its own encoder (q_layout): another one named beside it would go unused
            raise ConfigError(f"agent.encoder={self.encoder!r} does not apply with agent.network={self.network!r}, "
                              "a conv net of its own; set agent.network='mlp' to use agent.encoder, or leave "
                              "agent.encoder='auto'")
        self.require_sizes("hidden", linear_ok=True)
        self.require("in (0, 1]", "tau")
        self.require(">= 1", "target_update_period", "batch_size")
        self.require("in [0, 1]", "epsilon_start", "epsilon_end")
        if self.epsilon_decay_steps < -1:
            raise ConfigError(f"agent.epsilon_decay_steps={self.epsilon_decay_steps} is not valid; it must be >= 0 "
                              "(0: constant epsilon_end), or -1 (a tenth of train.total_steps)")
        self.require("in (0, 1]", "epsilon_decay")
        self.require("> 0", "lr", "adam_eps", "huber_delta")  # Adam's eps 0 divides 0 by 0 where a gradient stays 0
        self.require("in [0, 1]", "gamma")

# `relayrl train dqn` / `algo = "dqn"`: what a config that names only algo and env.id gets beyond
# the classes' defaults (which the DQN presets build on). Stable-Baselines3's DQN is the anchor:
# 64x64 ReLU MLP, batch 32, Huber loss, gradient norm 10, epsilon 1 -> 0.05 over the first tenth
# of the run (agent.epsilon_decay_steps = -1: SB3's exploration_fraction 0.1), one gradient step
# every 4 env steps after 100 random ones, gamma 0.99, tau 1.
# Where relayrl differs, and why:
# - target copy every 250 gradient steps (1,000 env steps), not SB3's 10,000 env steps: with
#   learning starting after 100 steps, SB3's rate leaves small problems (CartPole, Acrobot) with a
#   handful of target updates in 100k steps, the reason its defaults are known to be weak there.
# - replay 100,000 transitions, not 1M: DQN is the algorithm run on pixels, where 1M 84x84 frames
#   are ~7 GB of RAM; on small problems 100,000 holds the whole default run anyway.
# - total_steps 100,000 (SB3 has no default).
DEFAULTS: dict[str, Any] = {
    "train": {"total_steps": 100_000, "initial_collect_steps": 100, "collect_steps": 4},
    "eval": {"interval": 10_000},
    "agent": {"hidden": [64, 64], "lr": 1e-4, "batch_size": 32, "target_update_period": 250, "grad_clip": 10.0,
              "epsilon_decay_steps": -1},
}
