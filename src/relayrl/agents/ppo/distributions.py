"""The action distributions PPO's losses and policies share: categorical over logits (one per
entry of a MultiDiscrete space, independent), independent Bernoullis over logits (MultiBinary),
and a diagonal Gaussian with a state-independent log std, optionally tanh-squashed into the bounds.

A continuous action is kept as the Gaussian sample u (what rollouts store: its log-probability
is what the ratio needs); the env receives clip(u, low, high), or loc + scale * tanh(u) with
tanh squashing (`squash_scale` below is that scale, (high - low) / 2).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
LOG_2 = math.log(2.0)


def log_prob_entropy(out: torch.Tensor, log_std: torch.Tensor | None, action: torch.Tensor,
                     squash_scale: torch.Tensor | None = None, nvec: tuple[int, ...] = (),
                     binary: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """log pi(action) [N] and the entropy [N] of the distribution `out` parameterises.

    `nvec` (MultiDiscrete): `out` holds one block of logits per entry, sizes nvec; `binary`
    (MultiBinary): `out` holds one Bernoulli logit per entry. Entries are independent: their
    log-probabilities and entropies add up.

    With `squash_scale` [A] the log-probability is that of the squashed action a = loc +
    scale * tanh(u): the Gaussian's minus sum log(scale * (1 - tanh(u)^2)) (the change of
    variables); its entropy has no closed form and is estimated by -log pi, as SB3's
    SquashedDiagGaussianDistribution does.
    """
    if binary:  # Bernoulli logits [N, A]
        a = action.reshape(out.shape).to(out.dtype)
        logp = -F.binary_cross_entropy_with_logits(out, a, reduction="none").sum(-1)
        entropy = F.binary_cross_entropy_with_logits(out, torch.sigmoid(out), reduction="none").sum(-1)
        return logp, entropy
    if log_std is None and len(nvec) > 1:  # one categorical per entry: [N, sum(nvec)], actions [N, k]
        a = action.reshape(out.shape[0], -1).long()
        parts = [log_prob_entropy(block, None, a[:, i]) for i, block in enumerate(out.split(list(nvec), dim=-1))]
        return torch.stack([p[0] for p in parts]).sum(0), torch.stack([p[1] for p in parts]).sum(0)
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
    squashing loc + scale * tanh(u), loc and scale the bounds' midpoint and half-width (clipped
    too: at tanh = +-1 that sum can round a float32 step past a bound)."""
    if tanh:
        u = (high + low) / 2 + (high - low) / 2 * torch.tanh(u)
    return torch.minimum(torch.maximum(u, low), high)


class EnvBounds:
    """The env action for a sample u (`to_bounds` into the bounds, or u itself where a policy has
    none: discrete or unbounded actions), with the bounds as tensors on `device`."""

    def __init__(self, bounds: tuple[np.ndarray, np.ndarray] | None, squash: str,
                 device: torch.device | None = None) -> None:
        self.limits = None if bounds is None else tuple(
            torch.as_tensor(b, dtype=torch.float32, device=device) for b in bounds)
        self.tanh = squash == "tanh"

    def __call__(self, u: torch.Tensor) -> torch.Tensor:
        if self.limits is None:
            return u
        low, high = self.limits
        return to_bounds(u, low, high, self.tanh)


def greedy_logits_action(out: torch.Tensor, nvec: tuple[int, ...], binary: bool) -> torch.Tensor:
    """The most likely action of logits `out`: argmax [N] (one categorical), argmax per entry
    [N, k] (MultiDiscrete), or logit > 0 as int8 [N, A] (MultiBinary)."""
    if binary:
        return (out > 0).to(torch.int8)
    if len(nvec) > 1:
        return torch.stack([block.argmax(dim=1) for block in out.split(list(nvec), dim=-1)], dim=1)
    return out.argmax(dim=1)
