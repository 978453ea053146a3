"""SAC's gradient steps (critics, actor, alpha), chosen once when the agent is built: the
autograd reference (the losses of `losses.py` + `backward()`); on CUDA, the reference replayed
from a CUDA graph (`nn.graphed`); on CPU, its hand-written twin for MLP networks
(`nn.mlp_fast`, `losses_fast.py`: the same losses, draws and steps, with less per-update
overhead). Both subclass the reference, overriding `__call__`; tests/test_sac_fast.py and
tests/test_graphed.py compare them with it."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, cast

import torch

from relayrl.agents.sac import losses_fast
from relayrl.agents.sac.losses import actor_loss, alpha_loss, critic_loss, critic_targets, tanh_gaussian
from relayrl.nn import MLP, TwinMLP, mlp_fast
from relayrl.nn.graphed import GraphedStep, compiled, cuda_graphs_enabled
from relayrl.optim import FastAdam
from relayrl.types import Batch

if TYPE_CHECKING:
    from relayrl.agents.sac.agent import SACAgent

Tensor = torch.Tensor


class SACUpdate:
    """The reference: the losses of `losses.py`, autograd, torch's norm clip, the optimizers.
    `update(batch)` is a critic step on soft TD targets, an actor step through the freshly
    updated critics and an alpha step towards the target entropy; the agent then moves the
    target critics."""

    def __init__(self, agent: SACAgent) -> None:
        self.p = agent  # its networks, optimizers and noise generator, which it builds, owns and checkpoints
        self.critic_params = list(agent.critic.parameters())
        self.actor_params = list(agent.actor.parameters())
        # The losses themselves unless RELAYRL_COMPILE asks (nn/graphed.py); their noise comes in.
        self.critic_loss, self.actor_loss = compiled(self.critic_losses), compiled(self.actor_losses)

    def _sample(self, obs: Tensor, noise: Tensor) -> tuple[Tensor, Tensor]:
        cfg = self.p.cfg
        out = self.p.actor(obs)  # [N, 2A]
        mean, log_std = out.chunk(2, dim=-1)
        log_std = log_std.clamp(cfg.log_std_min, cfg.log_std_max)
        return tanh_gaussian(mean, log_std, noise)  # actions in [-1, 1]: [N, A], [N]

    def critic_losses(self, batch: Batch, alpha: Tensor, noise: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The critics' loss on soft TD targets (next actions drawn with `noise` [N, A]), the TD
        errors and the first critic's Q [N] (both detached)."""
        p, cfg = self.p, self.p.cfg
        with torch.no_grad():
            next_a, next_logp = self._sample(batch.next_obs, noise)
            y = critic_targets(batch.reward, batch.discount, p.target_critic(batch.next_obs, next_a),
                               next_logp, alpha, cfg.reward_scale)  # [N]
        action = (batch.action.reshape(batch.action.shape[0], -1) - p.action_loc) / p.action_half  # [N, A]
        q = p.critic(batch.obs, action)  # [2, N]
        c_loss, td = critic_loss(q, y, batch.weight)
        return c_loss, td, q[0].detach()

    def actor_losses(self, obs: Tensor, weight: Tensor | None, alpha: Tensor, noise: Tensor) -> tuple[Tensor, Tensor]:
        """The actor's loss through the critics (actions drawn with `noise`) and log pi [N]."""
        a_pi, logp = self._sample(obs, noise)
        q_pi = self.p.critic(obs, a_pi, detach_params=True)  # [2, N]: grads to a only
        return actor_loss(logp, q_pi, alpha, weight), logp

    def _step(self, opt: FastAdam, params: Sequence[Tensor], loss: Tensor) -> None:
        opt.zero_grad()
        loss.backward()
        if self.p.cfg.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(params, self.p.cfg.grad_clip)
        opt.step()

    def __call__(self, batch: Batch) -> dict[str, Tensor]:
        p, cfg = self.p, self.p.cfg
        alpha = p.log_alpha.detach().exp()
        shape = (batch.reward.shape[0], p.action_loc.numel())  # [N, A]
        next_noise = torch.randn(shape, generator=p.gen, device=alpha.device)  # the critic step's, then the actor's
        noise = torch.randn(shape, generator=p.gen, device=alpha.device)
        c_loss, td, q = self.critic_loss(batch, alpha, next_noise)
        self._step(p.critic_opt, self.critic_params, c_loss)

        a_loss, logp = self.actor_loss(batch.obs, batch.weight, alpha, noise)  # through the updated critics
        self._step(p.actor_opt, self.actor_params, a_loss)

        if cfg.autotune_alpha:
            self._step(p.alpha_opt, [p.log_alpha], alpha_loss(p.log_alpha, logp, p.target_entropy))
        return {"critic_loss": c_loss.detach(), "actor_loss": a_loss.detach(), "alpha": alpha,
                "entropy": -logp.detach().mean(), "q": q, "td_error": td}


class HandWrittenSACUpdate(SACUpdate):
    """`SACUpdate` for MLP actor and critics (`mlp_fast.supports`), with the gradients by hand."""

    def __init__(self, agent: SACAgent) -> None:
        super().__init__(agent)
        # make_update checked mlp_fast.supports: a plain MLP actor and TwinMLP critics (the target a copy)
        self.actor = mlp_fast.MLPFast(cast(MLP, agent.actor))
        self.critic = mlp_fast.TwinMLPFast(cast(TwinMLP, agent.critic))
        self.target = mlp_fast.TwinMLPFast(cast(TwinMLP, agent.target_critic))
        self.actor_grads = mlp_fast.grad_buffers(agent.actor)[1]  # views of one flat buffer

    def _step_with(self, opt: FastAdam, grads: list[Tensor]) -> None:
        if self.p.cfg.grad_clip > 0:
            mlp_fast.clip_grad_norm_(grads, self.p.cfg.grad_clip)
        opt.step(grads)

    @torch.no_grad()
    def __call__(self, batch: Batch) -> dict[str, Tensor]:
        p, cfg = self.p, self.p.cfg
        lo, hi = cfg.log_std_min, cfg.log_std_max
        n, a_dim = batch.reward.shape[0], p.action_loc.numel()
        alpha = p.log_alpha.detach().exp()
        obs = batch.obs.reshape(n, -1).float()
        next_obs = batch.next_obs.reshape(n, -1).float()
        # The critic step leaves the actor as it was, so one actor pass over [obs; next_obs]
        # serves both the targets and the actor step: one matmul of 2N rows per layer instead
        # of two of N. The noise is drawn in the reference's order (next_obs's first).
        noise_next = torch.randn((n, a_dim), generator=p.gen, device=obs.device)
        noise = torch.randn((n, a_dim), generator=p.gen, device=obs.device)
        a_both, logp_both, actor_saved = losses_fast.sample_and_log_prob(
            self.actor, torch.cat([obs, next_obs]), torch.cat([noise, noise_next]), lo, hi)  # [2N, A], [2N]
        a_pi, next_a, logp, next_logp = a_both[:n], a_both[n:], logp_both[:n], logp_both[n:]
        next_q = self.target.forward(torch.cat([next_obs, next_a], dim=-1))[0]
        y = critic_targets(batch.reward, batch.discount, next_q, next_logp, alpha, cfg.reward_scale)  # [N]

        action = (batch.action.reshape(n, -1) - p.action_loc) / p.action_half  # [N, A]
        q, saved = self.critic.forward(torch.cat([obs, action], dim=-1))  # [2, N]
        c_loss, td = critic_loss(q, y, batch.weight)
        w = batch.weight
        gq = (q - y) * (1.0 / n if w is None else w / n)  # d (0.5 sum_c mean w td^2) / dq
        grads = self.critic.new_grads()
        self.critic.backward(gq, saved, grads)
        self._step_with(p.critic_opt, grads)
        del grads  # freed before the actor's pass allocates

        q_pi, saved = self.critic.forward(torch.cat([obs, a_pi], dim=-1))  # the updated critics
        a_loss = actor_loss(logp, q_pi, alpha, w)
        g_min = torch.full((n,), -1.0 / n, device=obs.device) if w is None else w * (-1.0 / n)
        gq_pi = torch.zeros_like(q_pi).scatter_(0, q_pi.min(dim=0).indices.unsqueeze(0), g_min.unsqueeze(0))
        g_x = self.critic.backward(gq_pi, saved, None, input_grad=True)  # [N, in]
        assert g_x is not None
        g_logp = alpha * (1.0 / n if w is None else w / n)  # d loss / d log pi, [N] or scalar
        g_out = losses_fast.actor_head_grad(g_x[:, -a_dim:], g_logp.expand(n), actor_saved, lo, hi)  # [N, 2A]
        self.actor.backward(g_out, actor_saved[0], self.actor_grads, rows=n)
        self._step_with(p.actor_opt, self.actor_grads)

        if cfg.autotune_alpha:  # d alpha_loss / d log_alpha
            self._step_with(p.alpha_opt, [-(logp.mean() + p.target_entropy).reshape(p.log_alpha.shape)])
        return {"critic_loss": c_loss, "actor_loss": a_loss, "alpha": alpha, "entropy": -logp.mean(),
                "q": q[0], "td_error": td}


class GraphedSACUpdate(SACUpdate):
    """`SACUpdate` replayed from a CUDA graph per batch signature (`nn.graphed.GraphedStep`); the
    training noise's generator is registered with each graph, so replays draw fresh noise."""

    def __init__(self, agent: SACAgent) -> None:
        super().__init__(agent)
        self.graphed = GraphedStep(self._reference, generators=[agent.gen])

    def _reference(self, *fields: Tensor | None) -> dict[str, Tensor]:
        return SACUpdate.__call__(self, Batch(*cast("tuple[Any, ...]", fields)))  # the fields `__call__` passed

    def __call__(self, batch: Batch) -> dict[str, Tensor]:
        return self.graphed(*batch)


def make_update(agent: SACAgent, hand_written: bool = True) -> SACUpdate:
    """The step of the module doc (RELAYRL_CUDA_GRAPHS=0 turns graphs off, `hand_written=False` the twin)."""
    if cuda_graphs_enabled(agent.log_alpha.device):
        return GraphedSACUpdate(agent)
    twin = hand_written and mlp_fast.supports(agent.actor) and mlp_fast.supports(agent.critic)
    return HandWrittenSACUpdate(agent) if twin else SACUpdate(agent)
