"""PPO agent: owns the actor / critic networks, the optimizer, the schedules and counters.

`train(rollout)` takes one rollout ([T, B] steps, as `replay.rollouts.RolloutWriter` writes
it, consumed once), computes the old log-probabilities and values with the networks the
rollout was collected with (nothing has trained since), GAE(lambda), then `n_epochs`
epochs of shuffled minibatches: clipped surrogate + vf_coef * value loss - ent_coef *
entropy, one Adam step each after a global grad-norm clip.

With `normalize_reward` the rollout's rewards are scaled (`normalize.RewardScaler`, whose
state is the agent's) before GAE; with `normalize_obs` the observation statistics, buffers of
the policy network, take in the rollout's observations after training on it, so a rollout's
old log-probabilities come from exactly the policy that collected it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from relayrl.agents.ppo.advantages import gae
from relayrl.agents.ppo.config import PPOConfig
from relayrl.agents.ppo.device_policy import PPODevicePolicy
from relayrl.agents.ppo.distributions import log_prob_entropy
from relayrl.agents.ppo.losses import explained_variance
from relayrl.agents.ppo.networks import PolicyNet, PPONetworks
from relayrl.agents.ppo.normalize import RewardScaler
from relayrl.agents.ppo.policy import PPOCollectPolicy, PPOPolicy
from relayrl.agents.ppo.update import make_update
from relayrl.core import Agent
from relayrl.errors import UserError
from relayrl.nn.modes import evaluating
from relayrl.optim import FastAdam
from relayrl.schedules import linear_schedule
from relayrl.seeding import restore_generator
from relayrl.specs import ArraySpec, Spec, describe, spec_state


class PPOAgent(Agent):
    """`hand_written=False` runs the autograd update even where the hand-written one models
    the networks (tests compare the two)."""

    undefined_metrics = frozenset({"explained_variance"})  # NaN for a rollout of equal returns

    def __init__(self, obs_spec: Spec, action_spec: Spec, cfg: PPOConfig, device: torch.device,
                 rng: np.random.Generator, total_steps: int = 0, hand_written: bool = True) -> None:
        self.cfg = cfg
        self.device = device
        self.rng = rng  # collect-policy noise, checkpointed with the agent
        self.action_spec = action_spec
        self.obs_spec = obs_spec
        self.net = PPONetworks(obs_spec, action_spec, cfg.hidden, cfg.activation, cfg.shared,
                               cfg.log_std_init, cfg.normalize_obs, cfg.encoder).to(device)
        # tanh squashing: the log-probabilities are those of loc + scale * tanh(u). The scale adds a
        # constant to them, which a dimension with low == high (one value) leaves out instead of log 0.
        bounds = self._bounds()
        self.squash_scale: torch.Tensor | None = None
        if cfg.squash == "tanh" and bounds is not None:
            low, high = bounds
            if not (np.isfinite(low).all() and np.isfinite(high).all()):
                raise UserError(f"agent.squash='tanh' squashes actions into finite bounds; this env's action space "
                                f"is {describe(action_spec)}: use agent.squash='clip' (the default)")
            self.squash_scale = torch.as_tensor(np.where(high > low, (high - low) / 2, 1.0), dtype=torch.float32,
                                                device=device)
        self.reward_scaler = RewardScaler(cfg.gamma) if cfg.normalize_reward else None
        self.params = list(self.net.parameters())
        self.opt = FastAdam(self.params, lr=cfg.lr, eps=1e-5)  # SB3's PPO eps
        self.lr_at = linear_schedule(cfg.lr, cfg.lr_end if cfg.lr_end >= 0 else cfg.lr, total_steps)
        self.clip_at = linear_schedule(cfg.clip_range, cfg.clip_range_end if cfg.clip_range_end >= 0
                                       else cfg.clip_range, total_steps)
        self.clip_range = cfg.clip_range
        self.gen = torch.Generator()  # minibatch shuffles (on the CPU: the same on any device)
        self.gen.manual_seed(int(rng.integers(2**62)))
        self.train_step = 0
        self.update = make_update(self.net, self.opt, cfg, self.evaluate_actions, self.squash_scale is not None,
                                  hand_written)

    def _bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        s = self.action_spec
        if not isinstance(s, ArraySpec) or self.net.discrete:
            return None
        assert s.low is not None and s.high is not None  # action_head refuses a Box without them
        return s.low, s.high

    def collect_policy(self, env_step: Callable[[], int] | None = None,
                       network: torch.nn.Module | None = None) -> PPOPolicy:
        net = self._acting(network)
        return PPOCollectPolicy(net, net.log_std, self._bounds(), self.device, False, self.rng,
                                self.cfg.squash, self.net.head)

    def _acting(self, network: torch.nn.Module | None) -> PolicyNet:
        """The policy network a collect policy runs: an actor's copy of `policy_network()`, or
        (None) the agent's own."""
        net = network if network is not None else self.net.policy
        if not isinstance(net, PolicyNet):
            raise TypeError(f"a PPO collect policy runs a copy of policy_network(), not {type(net).__name__}")
        return net

    def eval_policy(self) -> PPOPolicy:
        return PPOPolicy(self.net.policy, self.net.policy.log_std, self._bounds(), self.device, True,
                         squash=self.cfg.squash, head=self.net.head)

    def policy_network(self) -> torch.nn.Module:
        return self.net.policy

    def device_collect_policy(self, network: torch.nn.Module | None = None) -> PPODevicePolicy:
        net = self._acting(network)
        if self.net.head.binary or len(self.net.head.nvec) > 1:
            raise UserError("PPO on a stateless torch env takes Discrete or Box actions")
        # The env gets the sample clipped, or tanh-squashed where the config has agent.squash = "tanh".
        return PPODevicePolicy(net, net.log_std, self._bounds(), self.device,
                               int(self.rng.integers(2**62)), self.cfg.squash)

    def scalars(self, env_steps: int) -> dict[str, float]:
        return {"learning_rate": float(self.lr_at(env_steps)), "clip_range": float(self.clip_at(env_steps))}

    def set_progress(self, env_steps: int) -> None:
        self.opt.lr = self.lr_at(env_steps)
        self.clip_range = self.clip_at(env_steps)

    def evaluate_actions(self, obs: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """(log pi(action | obs) [N], entropy [N], V(obs) [N]) under the current networks, for
        actions as rollouts hold them (continuous: the Gaussian samples, before clipping)."""
        out, values = self.net(obs)
        head = self.net.head
        logp, entropy = log_prob_entropy(out, self.net.policy.log_std, action, self.squash_scale, head.nvec,
                                         head.binary)
        return logp, entropy, values

    def train(self, rollout: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        cfg = self.cfg
        r = {k: v[0].to(self.device) for k, v in rollout.items()}  # one item: [T, B, ...]
        t, b = r["reward"].shape
        n = t * b
        obs, action = r["obs"].flatten(0, 1), r["action"].flatten(0, 1)  # [T * B, ...]
        # the rollout's log-probs and values in eval mode, as its actions were taken (a user's
        # encoder: Dropout off), as SB3 stores them while it collects
        with torch.no_grad(), evaluating(self.net):
            old_logp, _, values = self.evaluate_actions(obs, action)
            next_values = self.net(r["next_obs"].flatten(0, 1))[1]
        reward = r["reward"].float()
        if self.reward_scaler is not None:
            reward = self.reward_scaler(reward, r["terminated"] | r["truncated"])
        adv, returns = gae(reward, values.reshape(t, b), next_values.reshape(t, b),
                           r["terminated"], r["truncated"], cfg.gamma, cfg.gae_lambda)
        adv, returns = adv.reshape(-1), returns.reshape(-1)
        orders = torch.stack([torch.randperm(n, generator=self.gen) for _ in range(cfg.n_epochs)])
        if self.device.type == "cuda":  # pinned, so the copy does not make the host wait for the GPU
            orders = orders.pin_memory()
        orders = orders.to(self.device, non_blocking=True)
        sums = self.update.epochs((obs, action, old_logp, values, adv, returns), orders, self.clip_range)
        steps = cfg.n_epochs * -(-n // cfg.batch_size)
        self.train_step += steps
        if self.net.policy.obs_norm is not None:
            self.net.policy.obs_norm.update(obs)  # after training: the next rollout's policy
        means = sums / steps
        return {"policy_loss": means[0], "value_loss": means[1], "entropy": means[2], "approx_kl": means[3],
                "clip_fraction": means[4], "loss": means[5], "explained_variance": explained_variance(values, returns)}

    def policy_state(self) -> dict[str, Any]:
        p = self.net.policy
        state: dict[str, Any] = {
            "kind": "ppo", "discrete": self.net.discrete, "obs_space": spec_state(self.obs_spec),
            "action_space": spec_state(self.action_spec), "encoder": self.cfg.encoder,
            "obs_dim": p.mlp.layers[0].in_features, "hidden": list(self.cfg.hidden), "action_dim": p.out,
            "activation": self.cfg.activation, "state_dict": self.net.saved_head(),
        }
        if p.log_std is not None:
            low, high = self._bounds()  # type: ignore[misc]
            # the env's own bounds (a float64 Box's too): the loaded policy's action_space and clip use them
            state.update(log_std=p.log_std.detach().cpu().tolist(), action_low=np.asarray(low, np.float64),
                         action_high=np.asarray(high, np.float64), squash=self.cfg.squash)
        if p.obs_norm is not None:
            state.update(p.obs_norm.saved())
        return state

    def state_dict(self) -> dict[str, Any]:
        return {"net": self.net.state_dict(), "opt": self.opt.state_dict(), "train_step": self.train_step,
                "clip_range": self.clip_range, "rng": self.rng.bit_generator.state, "gen": self.gen.get_state(),
                "reward_scaler": None if self.reward_scaler is None else self.reward_scaler.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.net.load_state_dict(state["net"])
        self.opt.load_state_dict(state["opt"])
        self.train_step = int(state["train_step"])
        self.clip_range = float(state["clip_range"])
        self.rng.bit_generator.state = state["rng"]
        restore_generator(self.gen, state["gen"])  # saved on a GPU, resumed on a CPU too
        if self.reward_scaler is not None:
            self.reward_scaler.load_state_dict(state["reward_scaler"])
