"""PPO hyperparameters (Schulman et al. 2017, with the defaults of Stable-Baselines3's PPO).

A rollout is `train.collect_steps` env steps (`train.collect_steps / env.num_envs` per env
copy, SB3's n_steps), collected with the current policy, trained on for `n_epochs` epochs of
shuffled minibatches of `batch_size` steps, then dropped.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from relayrl.config_fields import ACTIVATION_NAMES, Section
from relayrl.errors import ConfigError

LOG_STD_INIT_MAX = 20.0  # a std of e^20 (4.9e8) is already no policy


@dataclass
class PPOConfig(Section):
    SECTION = "agent"
    NETWORK = ("hidden", "activation", "encoder", "shared", "squash", "normalize_obs")
    SCHEDULES = (("lr", "lr_end"), ("clip_range", "clip_range_end"))

    hidden: list[int] = field(default_factory=lambda: [64, 64])  # hidden sizes of actor and critic; []: linear heads
    activation: str = "tanh"  # relu | tanh | elu | leaky_relu | silu | gelu
    # observation encoder: auto (one-hot for Discrete / MultiDiscrete, a conv net for uint8 images 0..255,
    # each entry of a Dict / Tuple as that, flattened otherwise) | flatten | nature_cnn | small_cnn (float images too) |
    # package.module:make (your own: make(observation_space) returns a torch module, batch -> [B, features])
    encoder: str = "auto"
    shared: bool = False  # true: one MLP whose last layer holds the policy and value heads
    lr: float = 3e-4  # Adam's learning rate
    lr_end: float = -1.0  # < 0: constant lr; else linear in env steps to lr_end at train.total_steps
    clip_range: float = 0.2  # the surrogate's ratio clip
    clip_range_end: float = -1.0  # < 0: constant clip_range; else linear to clip_range_end at train.total_steps
    # value clipping as PPO2 / CleanRL: the larger of the squared errors of the value and of the value
    # clipped to old value +- this (SB3's clip_range_vf takes the clipped one only); 0: no value clipping
    clip_range_vf: float = 0.0
    n_epochs: int = 10  # passes over each rollout
    batch_size: int = 64  # steps per minibatch
    gamma: float = 0.99  # discount factor
    gae_lambda: float = 0.95  # GAE's lambda: 1 is Monte Carlo returns, 0 is one-step TD
    ent_coef: float = 0.0  # weight of the entropy bonus
    vf_coef: float = 0.5  # weight of the value loss
    max_grad_norm: float = 0.5  # global gradient-norm clip over all parameters; 0 disables
    normalize_advantage: bool = True  # per-minibatch advantage normalisation
    log_std_init: float = 0.0  # continuous actions: the initial state-independent log std
    squash: str = "clip"  # continuous: clip | tanh: the Gaussian sample clipped to, or tanh-squashed into, the bounds
    normalize_obs: bool = False  # running observation normalisation as SB3's VecNormalize, saved with the policy
    normalize_reward: bool = False  # rewards / running std of each env copy's discounted return (VecNormalize)

    def over_total_steps(self) -> list[str]:
        return [f"agent.{k}={getattr(self, k)}" for k in ("lr_end", "clip_range_end") if getattr(self, k) >= 0]

    def validate(self) -> None:
        self.require_encoder(self.encoder)
        self.require_choice(squash=("clip", "tanh"), activation=ACTIVATION_NAMES)
        self.require_sizes("hidden", linear_ok=True)
        self.require("> 0", "lr", "clip_range")
        self.require(">= 0", "clip_range_vf", note=" (0: unclipped)")
        self.require(">= 1", "n_epochs", "batch_size")
        self.require("in [0, 1]", "gamma", "gae_lambda")
        self.require(">= 0", "ent_coef", "vf_coef", "max_grad_norm")
        if abs(self.log_std_init) > LOG_STD_INIT_MAX:  # exp() of more overflows float32 (or flushes to 0)
            raise ConfigError(f"agent.log_std_init={self.log_std_init} is not valid; it must be in "
                              f"[-{LOG_STD_INIT_MAX:g}, {LOG_STD_INIT_MAX:g}] (a std of e^x; SB3's default 0: std 1)")

    def check_rollout(self, steps: int) -> None:
        if self.batch_size > steps:
            raise ConfigError(f"agent.batch_size={self.batch_size} is more than one rollout ({steps} env steps: "
                              "train.collect_steps over whole batched steps): a minibatch is part of a rollout; "
                              "lower agent.batch_size or raise train.collect_steps")


# `relayrl train ppo` / `algo = "ppo"`: what a config that names only algo and env.id gets beyond
# the classes' own defaults (the agent section above is SB3's PPO already). SB3's rollout: n_steps
# 2048 x 1 env, each step collected by the current policy. SB3 has no total_steps; 100,000 is
# where its defaults reach ~500 on CartPole-v1 (docs/config.md, README "Your own env").
DEFAULTS: dict[str, Any] = {
    "train": {"total_steps": 100_000, "initial_collect_steps": 0, "collect_steps": 2048,
              "checkpoint_interval": 20_480, "policy_save_interval": 10_240, "log_interval": 2048},
    "eval": {"interval": 10_240},  # every 5 rollouts
}
