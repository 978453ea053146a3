"""PPO's losses as pure functions of tensors (Schulman et al. 2017; SB3's scaling)."""

from __future__ import annotations

import torch


def normalize(advantages: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """(A - mean) / (std + eps) over the minibatch; a single element is left as it is (its
    std is undefined)."""
    if advantages.numel() < 2:
        return advantages
    return (advantages - advantages.mean()) / (advantages.std() + eps)


def policy_loss(log_prob: torch.Tensor, old_log_prob: torch.Tensor, advantages: torch.Tensor,
                clip_range: float | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The clipped surrogate -E[min(r A, clip(r, 1-e, 1+e) A)], r = pi/pi_old; with the
    approximate KL E[(r - 1) - log r] and the fraction of clipped ratios (both detached).
    `clip_range` may be a 0-d tensor (a CUDA graph's, whose schedule moves it in place)."""
    log_ratio = log_prob - old_log_prob
    ratio = log_ratio.exp()
    unclipped = ratio * advantages
    # Both bounds floats or both tensors, which clamp's overloads take; mypy splits the union per argument.
    clipped = ratio.clamp(1.0 - clip_range, 1.0 + clip_range) * advantages  # type: ignore[arg-type]
    loss = -torch.minimum(unclipped, clipped).mean()
    with torch.no_grad():
        approx_kl = ((ratio - 1.0) - log_ratio).mean()
        clip_fraction = ((ratio - 1.0).abs() > clip_range).float().mean()
    return loss, approx_kl, clip_fraction


def value_loss(values: torch.Tensor, old_values: torch.Tensor, returns: torch.Tensor,
               clip_range_vf: float = 0.0) -> torch.Tensor:
    """E[(V - R)^2]; with clip_range_vf > 0, the larger of that and the error of V clipped to
    old V +- clip_range_vf (PPO2's value clipping)."""
    err = (values - returns).square()
    if clip_range_vf <= 0:
        return err.mean()
    v_clipped = old_values + (values - old_values).clamp(-clip_range_vf, clip_range_vf)
    return torch.maximum(err, (v_clipped - returns).square()).mean()


def explained_variance(values: torch.Tensor, returns: torch.Tensor) -> torch.Tensor:
    """1 - Var[R - V] / Var[R]: 1 for perfect values, 0 for a constant; NaN when Var[R] = 0
    (undefined, as in SB3 and CleanRL). No host sync: the choice is made on the device."""
    var = returns.var(unbiased=False)
    return torch.where(var > 0, 1.0 - (returns - values).var(unbiased=False) / var, torch.full_like(var, float("nan")))
