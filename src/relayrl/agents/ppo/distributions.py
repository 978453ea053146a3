"""The action distributions PPO's losses and policies share: categorical over logits, and a
diagonal Gaussian with a state-independent log std."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


def log_prob_entropy(out: torch.Tensor, log_std: torch.Tensor | None,
                     action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """log pi(action) [N] and the entropy [N] of the distribution `out` parameterises."""
    if log_std is None:  # categorical over logits [N, A]
        logp_all = F.log_softmax(out, dim=-1)
        logp = logp_all.gather(1, action.reshape(-1, 1).long())[:, 0]
        return logp, -(logp_all.exp() * logp_all).sum(-1)
    a = action.reshape(out.shape).to(out.dtype)
    z = (a - out) * torch.exp(-log_std)
    logp = (-0.5 * z.square() - log_std - LOG_SQRT_2PI).sum(-1)
    entropy = (log_std + 0.5 + LOG_SQRT_2PI).sum().expand(out.shape[0])
    return logp, entropy
