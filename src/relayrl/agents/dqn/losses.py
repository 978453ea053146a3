"""DQN / Double DQN loss as a pure function: no optimizer, no logging, no state."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from relayrl.types import Batch


def td_targets(
    online: nn.Module, target: nn.Module | None, batch: Batch, *, double: bool, target_q: torch.Tensor | None = None
) -> torch.Tensor:
    """r + discount * Q_target(s', a*), with a* = argmax Q_target (DQN) or Q_online (Double DQN).

    `batch.discount` already holds gamma^n, and 0 where the episode terminated, so truncated
    episodes bootstrap and terminated ones do not. `target=None` means no target network:
    the online net's current weights give the targets (TF-Agents' default
    target_update_period=1, tau=1.0 is exactly this), and Double DQN equals DQN. `target_q`
    [N, A]: `target(batch.next_obs)` when the caller computed it ahead (`DQNAgent.prepare`).
    """
    with torch.no_grad():
        if target is None:
            next_v = online(batch.next_obs).max(dim=1).values  # [N]
        else:
            if target_q is None:
                target_q = target(batch.next_obs)  # [N, A]
            if double:
                # van Hasselt et al. 2016: select with the online net, evaluate with the target net.
                best = online(batch.next_obs).argmax(dim=1, keepdim=True)  # [N, 1]
                next_v = target_q.gather(1, best).squeeze(1)  # [N]
            else:
                next_v = target_q.max(dim=1).values  # [N]
        return torch.addcmul(batch.reward, batch.discount, next_v)  # [N]


def dqn_loss(online: nn.Module, target: nn.Module | None, batch: Batch, *, double: bool, loss: str = "huber",
             huber_delta: float = 1.0, target_q: torch.Tensor | None = None
             ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Mean over the batch of the (importance-weighted) element-wise TD loss.

    `mse` is the element-wise squared error (x - y)^2 without 1/2, like TF-Agents'
    `element_wise_squared_loss`; `huber` is SmoothL1 with `huber_delta`.
    """
    y = td_targets(online, target, batch, double=double, target_q=target_q)  # [N]
    q = online(batch.obs).gather(1, batch.action.long().unsqueeze(1)).squeeze(1)  # [N]
    # Without weights, the fused mean reductions are one autograd node instead of three.
    reduction = "mean" if batch.weight is None else "none"
    if loss == "mse":
        value = F.mse_loss(q, y, reduction=reduction)
    else:
        value = F.huber_loss(q, y, reduction=reduction, delta=huber_delta)
    if batch.weight is not None:
        value = (value * batch.weight).mean()
    # Unreduced on purpose: reducing costs ops on every step, the logger reduces when it logs.
    return value, {"loss": value.detach(), "q": q.detach(), "td_error": (q - y).detach()}
