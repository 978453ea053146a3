"""The action distributions PPO's losses and policies share: categorical over logits, and a
diagonal Gaussian with a state-independent log std, optionally tanh-squashed into the bounds.

A continuous action is kept as the Gaussian sample u (what rollouts store: its log-probability
is what the ratio needs); the env receives clip(u, low, high), or loc + scale * tanh(u) with
tanh squashing (`squash_scale` below is that scale, (high - low) / 2).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
LOG_2 = math.log(2.0)


def log_prob_entropy(out: torch.Tensor, log_std: torch.Tensor | None, action: torch.Tensor,
                     squash_scale: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """log pi(action) [N] and the entropy [N] of the distribution `out` parameterises.

    With `squash_scale` [A] the log-probability is that of the squashed action a = loc +
    scale * tanh(u): the Gaussian's minus sum log(scale * (1 - tanh(u)^2)) (the change of
    variables); its entropy has no closed form and is estimated by -log pi, as SB3's
    SquashedDiagGaussianDistribution does.
    """
    if log_std is None:  # categorical over logits [N, A]
        logp_all = F.log_softmax(out, dim=-1)
        logp = logp_all.gather(1, action.reshape(-1, 1).long())[:, 0]
        return logp, -(logp_all.exp() * logp_all).sum(-1)
    u = action.reshape(out.shape).to(out.dtype)
    z = (u - out) * torch.exp(-log_std)
    logp = (-0.5 * z.square() - log_std - LOG_SQRT_2PI).sum(-1)
    if squash_scale is not None:
        # log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u)), finite for any u
        log_det = torch.log(squash_scale.to(out.dtype)) + 2.0 * (LOG_2 - u - F.softplus(-2.0 * u))
        logp = logp - log_det.sum(-1)
        return logp, -logp
    entropy = (log_std + 0.5 + LOG_SQRT_2PI).sum().expand(out.shape[0])
    return logp, entropy


def to_bounds(u: torch.Tensor, low: torch.Tensor, high: torch.Tensor, tanh: bool) -> torch.Tensor:
    """The env action for a Gaussian sample (or mean) u: clip(u, low, high), or with tanh
    squashing loc + scale * tanh(u), loc and scale the bounds' midpoint and half-width."""
    if tanh:
        return (high + low) / 2 + (high - low) / 2 * torch.tanh(u)
    return torch.minimum(torch.maximum(u, low), high)
