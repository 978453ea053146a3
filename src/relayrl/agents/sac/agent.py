"""SAC agent: owns the actor, twin critics, their targets, alpha, optimizers and counters.

One `train(batch)` is: critic step on soft TD targets, actor step through the freshly
updated critics, alpha step towards the target entropy, Polyak update of the target critics
(the order of SB3 and TF-Agents). The losses are the pure functions of `losses.py`.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from relayrl.agents.sac import losses_fast
from relayrl.agents.sac.config import SACConfig
from relayrl.agents.sac.losses import actor_loss, alpha_loss, critic_loss, critic_targets, tanh_gaussian
from relayrl.agents.sac.networks import actor_network, check_action_spec, critic_network
from relayrl.nn import mlp_fast
from relayrl.optim import FastAdam
from relayrl.policies import TanhGaussianPolicy, network_state
from relayrl.schedules import linear_schedule
from relayrl.specs import Spec, flat_dim
from relayrl.types import Batch


class SACAgent:
    def __init__(self, obs_spec: Spec, action_spec: Spec, cfg: SACConfig, device: torch.device,
                 rng: np.random.Generator, total_steps: int = 0) -> None:
        self.cfg = cfg
        self.action_spec = check_action_spec(action_spec)
        self.device = device
        self.rng = rng  # collect-policy noise, checkpointed with the agent
        self.obs_spec = obs_spec
        self.actor = actor_network(obs_spec, self.action_spec, cfg.actor_hidden, cfg.activation, cfg.encoder).to(device)
        self.critic = critic_network(obs_spec, self.action_spec, cfg.critic_hidden, cfg.activation,
                                     cfg.encoder).to(device)
        self.target_critic = copy.deepcopy(self.critic).requires_grad_(False)
        self.log_alpha = torch.tensor(float(np.log(cfg.init_alpha)), device=device, requires_grad=True)
        self.actor_opt = FastAdam(self.actor.parameters(), lr=cfg.actor_lr)
        self.critic_opt = FastAdam(self.critic.parameters(), lr=cfg.critic_lr)
        self.alpha_opt = FastAdam([self.log_alpha], lr=cfg.alpha_lr)
        # agent.lr_end >= 0: each optimizer's lr linear in env steps to lr_end (set_progress), as
        # SB3 applies its one schedule to actor, critic and alpha; the fast path reads opt.lr too.
        self._lr_at = ([(opt, linear_schedule(lr, cfg.lr_end, total_steps)) for opt, lr in
                        ((self.actor_opt, cfg.actor_lr), (self.critic_opt, cfg.critic_lr),
                         (self.alpha_opt, cfg.alpha_lr))]
                       if cfg.lr_end >= 0 and total_steps > 0 else [])
        a_dim = int(np.prod(self.action_spec.shape))
        self.target_entropy = float(-a_dim if cfg.target_entropy is None else cfg.target_entropy)
        low, high = self.action_spec.low, self.action_spec.high
        # Replay holds env-scale actions; the critics see them rescaled to [-1, 1].
        self._loc = torch.as_tensor((high + low) / 2.0, dtype=torch.float32, device=device)
        self._half = torch.as_tensor((high - low) / 2.0, dtype=torch.float32, device=device)
        # Training noise from its own generator, so a checkpoint restores it exactly.
        self.gen = torch.Generator(device=device)
        self.gen.manual_seed(int(rng.integers(2**62)))
        self._critic_params = list(self.critic.parameters())
        self._target_params = list(self.target_critic.parameters())
        self._actor_params = list(self.actor.parameters())
        self._train_step = 0
        # Hand-written gradients (nn.mlp_fast, losses_fast.py) for the usual networks: the same
        # values as autograd's, with less per-update overhead on CPU. Tests set it to False to
        # compare against autograd.
        self.fast = mlp_fast.supports(self.actor) and mlp_fast.supports(self.critic)
        if self.fast:
            self._actor_fast = mlp_fast.MLPFast(self.actor)
            self._critic_fast = mlp_fast.TwinMLPFast(self.critic)
            self._target_fast = mlp_fast.TwinMLPFast(self.target_critic)
            self._actor_grads = mlp_fast.grad_buffers(self.actor)[1]  # views of one flat buffer

    @property
    def train_step(self) -> int:
        return self._train_step

    @property
    def alpha(self) -> float:
        return float(self.log_alpha.detach().exp())

    def _policy(self, deterministic: bool, network: torch.nn.Module | None = None) -> TanhGaussianPolicy:
        s = self.action_spec
        return TanhGaussianPolicy(network if network is not None else self.actor, s.low, s.high, self.device,
                                  deterministic, self.rng, self.cfg.log_std_min, self.cfg.log_std_max)

    def collect_policy(self, env_step: Callable[[], int] | None = None,
                       network: torch.nn.Module | None = None) -> TanhGaussianPolicy:
        return self._policy(deterministic=False, network=network)

    def policy_network(self) -> torch.nn.Module:
        return self.actor

    def eval_policy(self) -> TanhGaussianPolicy:
        return self._policy(deterministic=True)

    def set_progress(self, env_steps: int) -> None:
        """Follow schedules that run on env steps (the learning rates, with agent.lr_end >= 0)."""
        for opt, lr_at in self._lr_at:
            opt.lr = lr_at(env_steps)

    def scalars(self, env_steps: int) -> dict[str, float]:
        """For TensorBoard: charts/learning_rate (the actor's; the critics' and alpha's are in the config)."""
        return {"learning_rate": float(self.actor_opt.lr)}

    def _sample(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.actor(obs)  # [N, 2A]
        mean, log_std = out.chunk(2, dim=-1)
        log_std = log_std.clamp(self.cfg.log_std_min, self.cfg.log_std_max)
        noise = torch.randn(mean.shape, generator=self.gen, device=mean.device)
        return tanh_gaussian(mean, log_std, noise)  # actions in [-1, 1]: [N, A], [N]

    def train(self, batch: Batch) -> dict[str, torch.Tensor]:
        if self.fast:
            return self._train_fast(batch)
        cfg = self.cfg
        alpha = self.log_alpha.detach().exp()
        with torch.no_grad():
            next_a, next_logp = self._sample(batch.next_obs)
            y = critic_targets(batch.reward, batch.discount, self.target_critic(batch.next_obs, next_a),
                               next_logp, alpha, cfg.reward_scale)  # [N]
        action = (batch.action.reshape(batch.action.shape[0], -1) - self._loc) / self._half  # [N, A]
        q = self.critic(batch.obs, action)  # [2, N]
        c_loss, td = critic_loss(q, y, batch.weight)
        self._step(self.critic_opt, self._critic_params, c_loss)

        a_pi, logp = self._sample(batch.obs)
        q_pi = self.critic(batch.obs, a_pi, detach_params=True)  # [2, N]: updated critics, grads to a only
        a_loss = actor_loss(logp, q_pi, alpha, batch.weight)
        self._step(self.actor_opt, self._actor_params, a_loss)

        if cfg.autotune_alpha:
            self._step(self.alpha_opt, [self.log_alpha], alpha_loss(self.log_alpha, logp, self.target_entropy))
        self._count_step()
        return {"critic_loss": c_loss.detach(), "actor_loss": a_loss.detach(), "alpha": alpha,
                "entropy": -logp.detach().mean(), "q": q[0].detach(), "td_error": td}

    @torch.no_grad()
    def _count_step(self) -> None:
        """One more train step; the target critics follow by Polyak averaging every
        `target_update_period` steps (one fused op over every tensor)."""
        self._train_step += 1
        if self._train_step % self.cfg.target_update_period == 0:
            torch._foreach_lerp_(self._target_params, self._critic_params, self.cfg.tau)

    @torch.no_grad()
    def _train_fast(self, batch: Batch) -> dict[str, torch.Tensor]:
        """`train` with hand-written gradients: the same losses, draws and steps."""
        cfg = self.cfg
        lo, hi = cfg.log_std_min, cfg.log_std_max
        n, a_dim = batch.reward.shape[0], self._loc.numel()
        alpha = self.log_alpha.detach().exp()
        obs = batch.obs.reshape(n, -1).float()
        next_obs = batch.next_obs.reshape(n, -1).float()
        noise = torch.randn((n, a_dim), generator=self.gen, device=obs.device)
        next_a, next_logp, _ = losses_fast.sample_and_log_prob(self._actor_fast, next_obs, noise, lo, hi)
        next_q = self._target_fast.forward(torch.cat([next_obs, next_a], dim=-1))[0]
        y = critic_targets(batch.reward, batch.discount, next_q, next_logp, alpha, cfg.reward_scale)  # [N]

        action = (batch.action.reshape(n, -1) - self._loc) / self._half  # [N, A]
        q, saved = self._critic_fast.forward(torch.cat([obs, action], dim=-1))  # [2, N]
        c_loss, td = critic_loss(q, y, batch.weight)
        w = batch.weight
        gq = (q - y) * (1.0 / n if w is None else w / n)  # d (0.5 sum_c mean w td^2) / dq
        grads = self._critic_fast.new_grads()
        self._critic_fast.backward(gq, saved, grads)
        self._fast_step(self.critic_opt, grads)
        del grads  # freed before the actor's pass allocates

        noise = torch.randn((n, a_dim), generator=self.gen, device=obs.device)
        a_pi, logp, actor_saved = losses_fast.sample_and_log_prob(self._actor_fast, obs, noise, lo, hi)
        q_pi, saved = self._critic_fast.forward(torch.cat([obs, a_pi], dim=-1))  # the updated critics
        a_loss = actor_loss(logp, q_pi, alpha, w)
        g_min = torch.full((n,), -1.0 / n, device=obs.device) if w is None else w * (-1.0 / n)
        gq_pi = torch.zeros_like(q_pi).scatter_(0, q_pi.min(dim=0).indices.unsqueeze(0), g_min.unsqueeze(0))
        g_x = self._critic_fast.backward(gq_pi, saved, None, input_grad=True)  # [N, in]
        assert g_x is not None
        g_logp = alpha * (1.0 / n if w is None else w / n)  # d loss / d log pi, [N] or scalar
        g_out = losses_fast.actor_head_grad(g_x[:, -a_dim:], g_logp.expand(n), actor_saved, lo, hi)
        self._actor_fast.backward(g_out, actor_saved[0], self._actor_grads, rows=n)
        self._fast_step(self.actor_opt, self._actor_grads)

        if cfg.autotune_alpha:  # d alpha_loss / d log_alpha
            self._fast_step(self.alpha_opt, [-(logp.mean() + self.target_entropy).reshape(self.log_alpha.shape)])
        self._count_step()
        return {"critic_loss": c_loss, "actor_loss": a_loss, "alpha": alpha, "entropy": -logp.mean(),
                "q": q[0], "td_error": td}

    def _fast_step(self, opt: FastAdam, grads: list[torch.Tensor]) -> None:
        if self.cfg.grad_clip > 0:
            mlp_fast.clip_grad_norm_(grads, self.cfg.grad_clip)
        opt.step(grads)

    def _step(self, opt: FastAdam, params: list[torch.Tensor], loss: torch.Tensor) -> None:
        opt.zero_grad()
        loss.backward()
        if self.cfg.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(params, self.cfg.grad_clip)
        opt.step()

    def policy_state(self) -> dict[str, Any]:
        s = self.action_spec
        return {
            "kind": "tanh_gaussian",
            **network_state(self.actor, self.obs_spec, self.cfg.encoder, self.cfg.actor_hidden, self.cfg.activation),
            "action_dim": flat_dim(s),
            "action_low": np.asarray(s.low, np.float32), "action_high": np.asarray(s.high, np.float32),
            "log_std_min": self.cfg.log_std_min, "log_std_max": self.cfg.log_std_max,
        }

    def state_dict(self) -> dict[str, Any]:
        return {
            "actor": self.actor.state_dict(), "critic": self.critic.state_dict(),
            "target_critic": self.target_critic.state_dict(), "log_alpha": self.log_alpha.detach().clone(),
            "actor_opt": self.actor_opt.state_dict(), "critic_opt": self.critic_opt.state_dict(),
            "alpha_opt": self.alpha_opt.state_dict(), "train_step": self._train_step,
            "rng": self.rng.bit_generator.state, "gen": self.gen.get_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.actor.load_state_dict(state["actor"])
        self.critic.load_state_dict(state["critic"])
        self.target_critic.load_state_dict(state["target_critic"])
        with torch.no_grad():
            self.log_alpha.copy_(state["log_alpha"])
        self.actor_opt.load_state_dict(state["actor_opt"])
        self.critic_opt.load_state_dict(state["critic_opt"])
        self.alpha_opt.load_state_dict(state["alpha_opt"])
        self._train_step = int(state["train_step"])
        self.rng.bit_generator.state = state["rng"]
        self.gen.set_state(state["gen"])
