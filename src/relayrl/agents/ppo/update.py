"""PPO's minibatch gradient step, chosen once when the agent is built: the autograd reference
(the losses of `losses.py` + `backward()`); on CUDA, a rollout's epochs of the reference
replayed from one CUDA graph (`nn.graphed`; it overrides `epochs`); elsewhere its hand-written
twin (`nn.mlp_fast`, `losses_fast.py`: the same loss, clip and Adam step up to float rounding,
with less per-minibatch overhead on CPU; it overrides `__call__`). Both subclass the reference;
tests/test_ppo_fast.py and tests/test_graphed.py compare them with it."""

from __future__ import annotations

import functools
from collections.abc import Callable

import torch

from relayrl.agents.ppo import losses_fast
from relayrl.agents.ppo.config import PPOConfig
from relayrl.agents.ppo.losses import normalize, policy_loss, value_loss
from relayrl.agents.ppo.networks import PPONetworks
from relayrl.nn import mlp_fast
from relayrl.nn.graphed import GraphedStep, compiled, cuda_graphs_enabled
from relayrl.optim import FastAdam

Tensor = torch.Tensor
# (obs, action) -> (log pi(action | obs) [N], entropy [N], V(obs) [N]): `PPOAgent.evaluate_actions`
EvaluateActions = Callable[[Tensor, Tensor], tuple[Tensor, ...]]


def run_epochs(step: Callable[..., Tensor], data: tuple[Tensor, ...], orders: Tensor, batch_size: int,
               clip_range: float | Tensor) -> Tensor:
    """`step` on each minibatch of `data` (obs, action, old log-probs, old values, advantages,
    returns: [N, ...] each) in the order of each row of `orders` ([epochs, N]); the sums of the
    steps' statistics."""
    sums = torch.zeros(6, device=orders.device)
    n = orders.shape[1]
    for order in orders:
        for start in range(0, n, batch_size):
            idx = order[start:start + batch_size]
            sums += step(*(x[idx] for x in data), clip_range)
    return sums


class PPOUpdate:
    """The reference: clipped surrogate + vf_coef * value loss - ent_coef * entropy, autograd,
    torch's global norm clip, the optimizer step."""

    def __init__(self, net: PPONetworks, opt: FastAdam, cfg: PPOConfig, evaluate_actions: EvaluateActions) -> None:
        self.params = list(net.parameters())
        self.opt, self.cfg, self.evaluate_actions = opt, cfg, evaluate_actions
        self.loss = compiled(self.losses)  # the losses themselves unless RELAYRL_COMPILE asks (nn/graphed.py)
        # A compiled graph specialises on a Python float's value: a clip range that a schedule
        # moves goes into it as a tensor, or every value would compile a graph of its own.
        self.clip_as_tensor = self.loss != self.losses  # (each `self.losses` is a new bound method: not `is`)
        self._clip = torch.tensor(float(cfg.clip_range), device=self.params[0].device)
        self._clip_value = float(cfg.clip_range)

    def clip_tensor(self, clip_range: float) -> Tensor:
        """`clip_range` as a 0-d tensor on the parameters' device, refilled only when a schedule
        moves it (a launch, on a GPU)."""
        if clip_range != self._clip_value:
            self._clip.fill_(clip_range)
            self._clip_value = clip_range
        return self._clip

    def epochs(self, data: tuple[Tensor, ...], orders: Tensor, clip_range: float) -> Tensor:
        """Every minibatch step of one rollout, minibatches of `agent.batch_size` (see `run_epochs`)."""
        clip = self.clip_tensor(clip_range) if self.clip_as_tensor else clip_range
        return run_epochs(self, data, orders, self.cfg.batch_size, clip)

    def losses(self, obs: Tensor, action: Tensor, old_logp: Tensor, old_values: Tensor, adv: Tensor,
               returns: Tensor, clip_range: float | Tensor) -> tuple[Tensor, Tensor]:
        """The minibatch's loss and [policy loss, value loss, entropy, approx KL, clip fraction,
        loss] (detached)."""
        cfg = self.cfg
        if cfg.normalize_advantage:
            adv = normalize(adv)
        logp, entropy, values = self.evaluate_actions(obs, action)
        pg_loss, approx_kl, clip_fraction = policy_loss(logp, old_logp, adv, clip_range)
        v_loss = value_loss(values, old_values, returns, cfg.clip_range_vf)
        ent_loss = -entropy.mean()  # -E[H]: ent_coef times it rewards entropy
        loss = pg_loss + cfg.ent_coef * ent_loss + cfg.vf_coef * v_loss
        return loss, torch.stack([pg_loss.detach(), v_loss.detach(), -ent_loss.detach(), approx_kl, clip_fraction,
                                  loss.detach()])

    def __call__(self, obs: Tensor, action: Tensor, old_logp: Tensor, old_values: Tensor, adv: Tensor,
                 returns: Tensor, clip_range: float | Tensor) -> Tensor:
        """One gradient step on a minibatch; returns the statistics of `losses`."""
        loss, stats = self.loss(obs, action, old_logp, old_values, adv, returns, clip_range)
        self.opt.zero_grad()
        loss.backward()
        if self.cfg.max_grad_norm > 0:
            torch.nn.utils.clip_grad_norm_(self.params, self.cfg.max_grad_norm)
        self.opt.step()
        return stats


class HandWrittenPPOUpdate(PPOUpdate):
    """`PPOUpdate` with the gradients by hand, where `supports` says it models the networks."""

    def __init__(self, net: PPONetworks, opt: FastAdam, cfg: PPOConfig, evaluate_actions: EvaluateActions) -> None:
        super().__init__(net, opt, cfg, evaluate_actions)
        assert net.critic is not None
        self.actor = mlp_fast.MLPFast(net.policy.mlp)
        self.critic = mlp_fast.MLPFast(net.critic)
        self.log_std = net.policy.log_std
        self.flat_grad, self.grads = mlp_fast.grad_buffers(net)  # views in net.parameters() order
        view = {id(p): g for p, g in zip(net.parameters(), self.grads, strict=True)}
        self.actor_grads = [view[id(p)] for p in net.policy.mlp.parameters()]
        self.critic_grads = [view[id(p)] for p in net.critic.parameters()]
        self.log_std_grad = None if self.log_std is None else view[id(self.log_std)]

    @staticmethod
    def supports(net: PPONetworks, cfg: PPOConfig, squashed: bool) -> bool:
        """Separate actor and critic MLPs on Box observations, one categorical or a Gaussian,
        without value clipping, tanh squashing or observation normalisation (whose
        log-probabilities / inputs the hand-written heads do not model)."""
        head, policy = net.head, net.policy
        return (net.critic is not None and cfg.clip_range_vf == 0 and not squashed and policy.obs_norm is None
                and policy.encoder is None and not head.binary and len(head.nvec) <= 1
                and mlp_fast.supports(policy.mlp) and mlp_fast.supports(net.critic))

    @torch.no_grad()
    def __call__(self, obs: Tensor, action: Tensor, old_logp: Tensor, old_values: Tensor, adv: Tensor,
                 returns: Tensor, clip_range: float | Tensor) -> Tensor:
        cfg = self.cfg
        if cfg.normalize_advantage:
            adv = normalize(adv)
        out, saved_actor = self.actor.forward(obs)
        values, saved_critic = self.critic.forward(obs)
        log_std = self.log_std
        g = losses_fast.head_grads(out, None if log_std is None else log_std.detach(), action, values[:, 0], returns,
                                   old_logp, adv, clip_range, cfg.ent_coef, cfg.vf_coef)
        self.actor.backward(g.out, saved_actor, self.actor_grads)
        self.critic.backward(g.value, saved_critic, self.critic_grads)
        if self.log_std_grad is not None:
            assert g.log_std is not None  # head_grads gives it where there is a log_std, as here
            self.log_std_grad.copy_(g.log_std)
        if cfg.max_grad_norm > 0:
            mlp_fast.clip_flat_grad_norm_(self.flat_grad, cfg.max_grad_norm)
        self.opt.step(self.grads)
        return g.stats


class GraphedPPOUpdate(PPOUpdate):
    """`PPOUpdate` whose epochs over a rollout (every minibatch's gather and step) replay from one
    CUDA graph per rollout signature (`nn.graphed.GraphedStep`): one launch per rollout instead
    of a dozen per minibatch. The clip range reaches the graph as a device tensor, so its
    schedule reaches the replays."""

    def __init__(self, net: PPONetworks, opt: FastAdam, cfg: PPOConfig, evaluate_actions: EvaluateActions) -> None:
        super().__init__(net, opt, cfg, evaluate_actions)
        self.graphed = GraphedStep(self._reference)

    def _reference(self, *tensors: Tensor) -> dict[str, Tensor]:
        *data, orders, clip_range = tensors
        step = functools.partial(PPOUpdate.__call__, self)
        return {"sums": run_epochs(step, tuple(data), orders, self.cfg.batch_size, clip_range)}

    def epochs(self, data: tuple[Tensor, ...], orders: Tensor, clip_range: float) -> Tensor:
        return self.graphed(*data, orders, self.clip_tensor(clip_range))["sums"]


def make_update(net: PPONetworks, opt: FastAdam, cfg: PPOConfig, evaluate_actions: EvaluateActions,
                squashed: bool, hand_written: bool = True) -> PPOUpdate:
    """The step of the module doc (RELAYRL_CUDA_GRAPHS=0 turns graphs off, `hand_written=False` the twin)."""
    if cuda_graphs_enabled(next(net.parameters()).device):
        return GraphedPPOUpdate(net, opt, cfg, evaluate_actions)
    if hand_written and HandWrittenPPOUpdate.supports(net, cfg, squashed):
        return HandWrittenPPOUpdate(net, opt, cfg, evaluate_actions)
    return PPOUpdate(net, opt, cfg, evaluate_actions)
