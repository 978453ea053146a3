"""PPO's loss gradients at the networks' heads, for the hand-written update of update.py.

The networks' backward passes are relayrl.nn.mlp_fast's; what is PPO's own is the gradient of
clipped surrogate + ent_coef * entropy loss + vf_coef * value loss with respect to the actor's
outputs (logits, or the Gaussian mean and its log std) and the critic's values. The maths is
that of `losses.py` and `distributions.py` (no value clipping); tests/test_ppo_fast.py checks
the update against those losses + `backward()`. Shapes: N minibatch rows, A action outputs.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F

from relayrl.agents.ppo.distributions import LOG_SQRT_2PI

Tensor = torch.Tensor


class HeadGrads(NamedTuple):
    stats: Tensor  # [policy loss, value loss, entropy, approx KL, clip fraction, loss]
    out: Tensor  # d loss / d actor outputs [N, A]
    log_std: Tensor | None  # d loss / d log_std [A] (continuous actions)
    value: Tensor  # d loss / d values [N, 1]


def _surrogate(logp: Tensor, old_logp: Tensor, adv: Tensor, clip_range: float | Tensor) -> tuple[Tensor, Tensor]:
    """(policy loss, approx KL, clip fraction) as `losses.policy_loss`, and d loss / d logp [N].

    d/dr of -min(r A, clip(r) A) is -A where the unclipped term is the smaller or the two are
    equal (inside the clip range, where torch's minimum splits the gradient between two equal
    branches of slope A), else 0 (the clipped term is flat there)."""
    n = logp.shape[0]
    log_ratio = logp - old_logp
    ratio = log_ratio.exp()
    unclipped = ratio * adv
    # Both bounds floats or both tensors, which clamp's overloads take; mypy splits the union per argument.
    clipped = ratio.clamp(1.0 - clip_range, 1.0 + clip_range) * adv  # type: ignore[arg-type]
    loss = -torch.minimum(unclipped, clipped).mean()
    approx_kl = ((ratio - 1.0) - log_ratio).mean()
    clip_fraction = ((ratio - 1.0).abs() > clip_range).float().mean()
    g_logp = (unclipped <= clipped) * (unclipped * (-1.0 / n))  # d loss / d r * r
    return torch.stack([loss, approx_kl, clip_fraction]), g_logp


@torch.no_grad()
def head_grads(out: Tensor, log_std: Tensor | None, action: Tensor, values: Tensor, returns: Tensor, old_logp: Tensor,
               adv: Tensor, clip_range: float | Tensor, ent_coef: float, vf_coef: float) -> HeadGrads:
    """The minibatch's statistics and the loss's gradients at the heads (advantages as the loss
    sees them, i.e. already normalised where the run normalises them)."""
    n = out.shape[0]
    if log_std is None:  # categorical over logits
        logp_all = F.log_softmax(out, dim=-1)
        idx = action.reshape(-1, 1).long()
        logp = logp_all.gather(1, idx)[:, 0]
        p = logp_all.exp()
        entropy = -(p * logp_all).sum(-1)
        surr, g_logp = _surrogate(logp, old_logp, adv, clip_range)
        # d logp_a / d logits = onehot(a) - p; d (-H) / d logits = p (log p + H)
        g_out = p * ((logp_all + entropy.unsqueeze(1)) * (ent_coef / n) - g_logp.unsqueeze(1))
        g_out.scatter_add_(1, idx, g_logp.unsqueeze(1))
        g_log_std = None
        ent_mean = entropy.mean()
    else:  # diagonal Gaussian, state-independent log std
        inv_std = torch.exp(-log_std)
        z = (action.reshape(out.shape).to(out.dtype) - out) * inv_std
        logp = (-0.5 * z.square() - log_std - LOG_SQRT_2PI).sum(-1)
        surr, g_logp = _surrogate(logp, old_logp, adv, clip_range)
        g = g_logp.unsqueeze(1)
        g_out = g * z * inv_std  # d logp / d mean = z / std
        g_log_std = (g * (z.square() - 1.0)).sum(0) - ent_coef  # entropy = sum(log_std) + const
        ent_mean = (log_std + 0.5 + LOG_SQRT_2PI).sum()
    err = values - returns
    v_loss = err.square().mean()
    loss = surr[0] - ent_coef * ent_mean + vf_coef * v_loss
    stats = torch.stack([surr[0], v_loss, ent_mean, surr[1], surr[2], loss])
    return HeadGrads(stats, g_out, g_log_std, (err * (2.0 * vf_coef / n)).unsqueeze(1))
