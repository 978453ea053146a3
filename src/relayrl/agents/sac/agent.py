"""SAC agent: owns the actor, twin critics, their targets, alpha, optimizers and counters;
`update.py` holds the gradient steps, in the order of SB3 and TF-Agents."""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from relayrl.agents.sac.config import SACConfig
from relayrl.agents.sac.networks import actor_network, check_action_spec, critic_network
from relayrl.agents.sac.update import make_update
from relayrl.core import Agent
from relayrl.optim import FastAdam
from relayrl.policies import TanhGaussianPolicy, network_state
from relayrl.schedules import linear_schedule
from relayrl.seeding import restore_generator
from relayrl.specs import Spec, flat_dim
from relayrl.types import Batch


class SACAgent(Agent):
    """`hand_written=False` runs the autograd update even where the hand-written one supports
    the networks (tests compare the two)."""

    def __init__(self, obs_spec: Spec, action_spec: Spec, cfg: SACConfig, device: torch.device,
                 rng: np.random.Generator, total_steps: int = 0, hand_written: bool = True) -> None:
        self.cfg = cfg
        self.action_spec = check_action_spec(action_spec)
        self.device = device
        self.rng = rng  # collect-policy noise, checkpointed with the agent
        self.obs_spec = obs_spec
        self.actor = actor_network(obs_spec, self.action_spec, cfg.actor_hidden, cfg.activation, cfg.encoder).to(device)
        self.critic = critic_network(obs_spec, self.action_spec, cfg.critic_hidden, cfg.activation,
                                     cfg.encoder).to(device)
        self.target_critic = copy.deepcopy(self.critic).requires_grad_(False).eval()  # as SB3's: eval mode
        self.log_alpha = torch.tensor(float(np.log(cfg.init_alpha)), device=device, requires_grad=True)
        self.actor_opt = FastAdam(self.actor.parameters(), lr=cfg.actor_lr)
        self.critic_opt = FastAdam(self.critic.parameters(), lr=cfg.critic_lr)
        self.alpha_opt = FastAdam([self.log_alpha], lr=cfg.alpha_lr)
        # each optimizer with its configured rate: the schedule starts from it, a resume restores it
        self._rates = ((self.actor_opt, cfg.actor_lr), (self.critic_opt, cfg.critic_lr), (self.alpha_opt, cfg.alpha_lr))
        # agent.lr_end >= 0: each optimizer's lr linear in env steps to lr_end (set_progress), as
        # SB3 applies its one schedule to actor, critic and alpha; both updates read opt.lr.
        self._lr_at = ([(opt, linear_schedule(lr, cfg.lr_end, total_steps)) for opt, lr in self._rates]
                       if cfg.lr_end >= 0 and total_steps > 0 else [])
        a_dim = int(np.prod(self.action_spec.shape))
        self.target_entropy = float(-a_dim if cfg.target_entropy is None else cfg.target_entropy)
        low, high = self.action_spec.low, self.action_spec.high
        assert low is not None and high is not None  # check_action_spec takes bounded Boxes only
        # [A] replay holds env-scale actions; the critics see them rescaled to [-1, 1] as (action - loc) / half
        self.action_loc = torch.as_tensor((high + low) / 2.0, dtype=torch.float32, device=device)
        self.action_half = torch.as_tensor((high - low) / 2.0, dtype=torch.float32, device=device)
        # Training noise from its own generator, so a checkpoint restores it exactly.
        self.gen = torch.Generator(device=device)
        self.gen.manual_seed(int(rng.integers(2**62)))
        self._critic_params: list[torch.Tensor] = list(self.critic.parameters())
        self._target_params: list[torch.Tensor] = list(self.target_critic.parameters())
        self.train_step = 0
        self._eval_policy: TanhGaussianPolicy | None = None
        self.update = make_update(self, hand_written)

    @property
    def alpha(self) -> float:
        return float(self.log_alpha.detach().exp())

    def _policy(self, deterministic: bool, network: torch.nn.Module | None = None) -> TanhGaussianPolicy:
        s = self.action_spec
        assert s.low is not None and s.high is not None  # check_action_spec takes bounded Boxes only
        return TanhGaussianPolicy(network if network is not None else self.actor, s.low, s.high, self.device,
                                  deterministic, self.rng, self.cfg.log_std_min, self.cfg.log_std_max)

    def collect_policy(self, env_step: Callable[[], int] | None = None,
                       network: torch.nn.Module | None = None) -> TanhGaussianPolicy:
        return self._policy(deterministic=False, network=network)

    def policy_network(self) -> torch.nn.Module:
        return self.actor

    def eval_policy(self) -> TanhGaussianPolicy:
        # One for the run: it reads the live actor, and on CUDA keeps its captured graphs.
        if self._eval_policy is None:
            self._eval_policy = self._policy(deterministic=True)
        return self._eval_policy

    def set_progress(self, env_steps: int) -> None:
        for opt, lr_at in self._lr_at:
            opt.lr = lr_at(env_steps)

    def scalars(self, env_steps: int) -> dict[str, float]:
        # the actor's; the critics' and alpha's follow from the config
        return {"learning_rate": float(self.actor_opt.lr)}

    def train(self, batch: Batch) -> dict[str, torch.Tensor]:
        metrics = self.update(batch)
        self.train_step += 1
        if self.train_step % self.cfg.target_update_period == 0:  # Polyak, one fused op over every tensor
            with torch.no_grad():
                torch._foreach_lerp_(self._target_params, self._critic_params, self.cfg.tau)
        return metrics

    def policy_state(self) -> dict[str, Any]:
        s = self.action_spec
        return {
            "kind": "tanh_gaussian",
            **network_state(self.actor, self.obs_spec, self.cfg.encoder, self.cfg.actor_hidden, self.cfg.activation),
            "action_dim": flat_dim(s),
            # the env's own bounds (a float64 Box's too): the loaded policy's action_space and clip use them
            "action_low": np.asarray(s.low, np.float64), "action_high": np.asarray(s.high, np.float64),
            "log_std_min": self.cfg.log_std_min, "log_std_max": self.cfg.log_std_max,
        }

    def state_dict(self) -> dict[str, Any]:
        return {
            "actor": self.actor.state_dict(), "critic": self.critic.state_dict(),
            "target_critic": self.target_critic.state_dict(), "log_alpha": self.log_alpha.detach().clone(),
            "actor_opt": self.actor_opt.state_dict(), "critic_opt": self.critic_opt.state_dict(),
            "alpha_opt": self.alpha_opt.state_dict(), "train_step": self.train_step,
            "rng": self.rng.bit_generator.state, "gen": self.gen.get_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.actor.load_state_dict(state["actor"])
        self.critic.load_state_dict(state["critic"])
        self.target_critic.load_state_dict(state["target_critic"])
        with torch.no_grad():
            # a fixed alpha (agent.autotune_alpha = false) is the config's, as a constant lr is
            saved = state["log_alpha"] if self.cfg.autotune_alpha else float(np.log(self.cfg.init_alpha))
            self.log_alpha.copy_(torch.as_tensor(saved))
        self.actor_opt.load_state_dict(state["actor_opt"])
        self.critic_opt.load_state_dict(state["critic_opt"])
        self.alpha_opt.load_state_dict(state["alpha_opt"])
        if not self._lr_at:
            # Constant learning rates are the config's, not the checkpoint's: a resume may change
            # them (--set agent.actor_lr=...). A schedule (agent.lr_end) sets them at every step.
            for opt, lr in self._rates:
                opt.lr = lr
        self.train_step = int(state["train_step"])
        self.rng.bit_generator.state = state["rng"]
        restore_generator(self.gen, state["gen"])  # saved on a GPU, resumed on a CPU too
