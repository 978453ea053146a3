"""SAC losses as pure functions of tensors: no modules, optimizers or randomness inside.

The agent runs the networks and draws the noise; these functions only do the arithmetic,
so tests can check them against values computed by hand.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

_LOG2 = math.log(2.0)


def tanh_gaussian(mean: torch.Tensor, log_std: torch.Tensor, noise: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """a = tanh(mean + std * noise) and log pi(a | s), summed over action dims.

    log pi(a) = log N(u; mean, std) - sum log(1 - tanh(u)^2), with the Jacobian term written
    as 2 (log 2 - u - softplus(-2u)), which stays finite where tanh(u) rounds to +-1
    (the form TF-Probability's TanhBijector uses).
    """
    u = mean + log_std.exp() * noise  # [N, A]
    log_normal = -0.5 * noise.square() - log_std - 0.5 * math.log(2.0 * math.pi)  # [N, A]
    log_det = 2.0 * (_LOG2 - u - F.softplus(-2.0 * u))  # [N, A]
    return torch.tanh(u), (log_normal - log_det).sum(dim=-1)  # [N, A], [N]


def critic_targets(reward: torch.Tensor, discount: torch.Tensor, next_q: torch.Tensor,
                   next_log_prob: torch.Tensor, alpha: torch.Tensor | float, reward_scale: float) -> torch.Tensor:
    """y = scale * r + discount * (min_i Q'_i(s', a') - alpha log pi(a' | s')).

    `discount` is gamma^n, 0 where the episode terminated (so truncation bootstraps);
    next_q [2, N] comes from the target critics. Returns [N], without gradient.
    """
    soft_v = next_q.min(dim=0).values - alpha * next_log_prob  # [N]
    return (reward_scale * reward + discount * soft_v).detach()


def critic_loss(q: torch.Tensor, y: torch.Tensor, weight: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """Sum over the twin critics of 0.5 * mean (importance-weighted) squared TD error.

    q [2, N], y [N]. Returns (loss, td_error [N] of the first critic, for priorities).
    """
    td = q - y  # [2, N]
    sq = td.square()
    if weight is not None:
        sq = sq * weight
    return 0.5 * sq.mean(dim=1).sum(), td[0].detach()


def actor_loss(log_prob: torch.Tensor, q_pi: torch.Tensor, alpha: torch.Tensor | float,
               weight: torch.Tensor | None = None) -> torch.Tensor:
    """mean(alpha log pi(a|s) - min_i Q_i(s, a)), a ~ pi; q_pi [2, N], log_prob [N]."""
    value = alpha * log_prob - q_pi.min(dim=0).values  # [N]
    return (value * weight).mean() if weight is not None else value.mean()


def alpha_loss(log_alpha: torch.Tensor, log_prob: torch.Tensor, target_entropy: float) -> torch.Tensor:
    """-mean(log_alpha * (log pi + target_entropy)): alpha rises while entropy is below target."""
    return -(log_alpha * (log_prob.detach() + target_entropy)).mean()
