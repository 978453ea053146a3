"""DQN agent: owns the networks, optimizer, target updates and counters; the loss is pure."""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np
import torch

from relayrl.agents.dqn.config import DQNConfig
from relayrl.agents.dqn.networks import conv_state_dict, q_layout, q_network
from relayrl.agents.dqn.update import make_update
from relayrl.core import Agent
from relayrl.optim import FastAdam
from relayrl.policies import EpsilonGreedyPolicy, GreedyPolicy, mlp_head, network_state
from relayrl.schedules import exponential_schedule, linear_schedule
from relayrl.specs import DiscreteSpec, Spec
from relayrl.types import Batch


class PreparedBatch(NamedTuple):
    """A chunk of batches (`Batch`'s fields) with the target network's Q-values of their next
    observations computed ahead (`DQNAgent.prepare`); the learner slices it row-wise."""

    obs: torch.Tensor  # [N, *obs_shape]
    action: torch.Tensor  # [N, *act_shape]
    reward: torch.Tensor  # [N]
    next_obs: torch.Tensor  # [N, *obs_shape]
    discount: torch.Tensor  # [N]
    weight: torch.Tensor | None  # [N]
    target_q: torch.Tensor  # [N, A] the target network's Q(next_obs, .)


class DQNAgent(Agent):
    """`hand_written=False` runs the autograd update even where the hand-written one supports
    the network (tests compare the two)."""

    def __init__(self, obs_spec: Spec, action_spec: Spec, cfg: DQNConfig, device: torch.device,
                 rng: np.random.Generator, total_steps: int = 0, hand_written: bool = True) -> None:
        self.cfg = cfg
        self.obs_spec = obs_spec
        self.action_spec = action_spec
        self.device = device
        self.rng = rng  # exploration randomness, checkpointed with the agent
        self.online = q_network(obs_spec, action_spec, cfg).to(device)
        # A target updated by a full copy after every step equals the online net at every
        # loss evaluation: keep none and let the loss share one forward pass.
        self.target = (None if cfg.target_update_period == 1 and cfg.tau >= 1.0
                       else copy.deepcopy(self.online).requires_grad_(False).eval())  # as SB3's: eval mode
        self.optimizer = FastAdam(self.online.parameters(), lr=cfg.lr, eps=cfg.adam_eps)
        self.train_step = 0
        self._eval_policy: GreedyPolicy | None = None
        self.epsilon_decay_steps = cfg.epsilon_decay_steps if cfg.epsilon_decay_steps >= 0 else total_steps // 10
        self._lr_at = (linear_schedule(cfg.lr, cfg.lr_end, total_steps)
                       if cfg.lr_end >= 0 and total_steps > 0 else None)
        self._online_params: list[torch.Tensor] = list(self.online.parameters())
        self._target_params: list[torch.Tensor] = list(self.target.parameters()) if self.target is not None else []
        self.update = make_update(self.online, self.target, self.optimizer, cfg, hand_written)

    def collect_policy(self, env_step: Callable[[], int], network: torch.nn.Module | None = None
                       ) -> EpsilonGreedyPolicy:
        assert isinstance(self.action_spec, DiscreteSpec)
        greedy = GreedyPolicy(network if network is not None else self.online, self.device)
        return EpsilonGreedyPolicy(greedy, self.action_spec.n, self.epsilon_schedule(), env_step, self.rng)

    def epsilon_schedule(self) -> Callable[[int], float]:
        """env step -> the probability of a random action."""
        c = self.cfg
        return (exponential_schedule(c.epsilon_start, c.epsilon_end, c.epsilon_decay)
                if c.epsilon_schedule == "exponential"
                else linear_schedule(c.epsilon_start, c.epsilon_end, self.epsilon_decay_steps))

    def scalars(self, env_steps: int) -> dict[str, float]:
        return {"epsilon": float(self.epsilon_schedule()(env_steps)), "learning_rate": float(self.optimizer.lr)}

    def policy_network(self) -> torch.nn.Module:
        return self.online

    def eval_policy(self) -> GreedyPolicy:
        # One for the run: it reads the live network, and on CUDA keeps its captured graphs.
        if self._eval_policy is None:
            self._eval_policy = GreedyPolicy(self.online, self.device)
        return self._eval_policy

    def set_progress(self, env_steps: int) -> None:
        if self._lr_at is not None:
            self.optimizer.lr = self._lr_at(env_steps)

    def prepare_horizon(self) -> int:
        if self.target is None or self.cfg.target_update_period == 1:
            return 0
        return self.cfg.target_update_period - self.train_step % self.cfg.target_update_period

    @torch.no_grad()
    def prepare(self, batch: Batch, steps: int) -> Batch | PreparedBatch:
        """The target network's Q-values of the chunk's next observations, computed ahead: one
        forward pass replaces `steps` small ones, with train()'s values up to float rounding."""
        if steps < 2 or steps > self.prepare_horizon():
            return batch
        next_obs = batch.next_obs.to(self.device, non_blocking=True)  # [steps * N, *obs_shape]
        # Blocks of 256 rows: one [8192, 256] activation is a fresh 8 MB allocation whose page
        # faults cost as much as the matmul saves (256 rows stay in cache and reuse memory),
        # and a chunk of pixel batches never needs all its conv activations at once.
        target_q = torch.cat([self.update.target_q(x) for x in next_obs.split(256)])  # [steps * N, A]
        return PreparedBatch(*batch, target_q=target_q)

    def train(self, batch: Batch | PreparedBatch) -> dict[str, torch.Tensor]:
        if isinstance(batch, PreparedBatch):
            metrics = self.update(Batch(*batch[:-1]), batch.target_q)
        else:
            metrics = self.update(batch, None)
        self.train_step += 1
        if self.target is not None and self.train_step % self.cfg.target_update_period == 0:
            self._update_target()
        return metrics

    @torch.no_grad()
    def _update_target(self) -> None:
        if self.cfg.tau >= 1.0:
            torch._foreach_copy_(self._target_params, self._online_params)
        else:
            # Polyak: target <- target + tau * (online - target), fused over all tensors.
            torch._foreach_lerp_(self._target_params, self._online_params, self.cfg.tau)

    def policy_state(self) -> dict[str, Any]:
        return {"kind": "q_greedy", "num_actions": mlp_head(self.online).layers[-1].out_features,
                **network_state(self.online, self.obs_spec, *q_layout(self.cfg))}

    def state_dict(self) -> dict[str, Any]:
        return {
            "online": self.online.state_dict(),
            "target": self.target.state_dict() if self.target is not None else None,
            "optimizer": self.optimizer.state_dict(),
            "train_step": self.train_step,
            "rng": self.rng.bit_generator.state,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.online.load_state_dict(conv_state_dict(state["online"]))
        if self.target is not None:
            self.target.load_state_dict(conv_state_dict(state["target"]))
        self.optimizer.load_state_dict(state["optimizer"])
        if self._lr_at is None:
            # A constant learning rate is the config's, not the checkpoint's: a resume may change it
            # (--set agent.lr=...). A schedule (agent.lr_end) sets it at every step.
            self.optimizer.lr = self.cfg.lr
        self.train_step = int(state["train_step"])
        self.rng.bit_generator.state = state["rng"]
