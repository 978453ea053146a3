"""The DQN loss and its gradients for MLP Q-networks, with the MLP's backward written out
(relayrl.nn.mlp_fast) instead of autograd's.

Why: on a CPU, autograd's bookkeeping and per-tensor clipping cost about as much as the
matmuls of a small Q-network's update; here the gradients go into one flat buffer (so
clipping is one norm and one multiply). `dqn_loss_and_grads` is pure like `dqn_loss`: same
inputs, same (loss, metrics), plus the gradients; `out` only says where to write them.
tests/test_dqn_fast.py checks it against `dqn_loss` + `backward()`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from relayrl.nn import MLP
from relayrl.nn.mlp_fast import MLPFast
from relayrl.types import Batch

Tensor = torch.Tensor


@torch.no_grad()
def dqn_loss_and_grads(
    online: MLP | MLPFast,
    target: MLP | MLPFast | None,
    batch: Batch,
    *,
    double: bool,
    loss: str = "huber",
    huber_delta: float = 1.0,
    target_q: Tensor | None = None,
    out: list[Tensor] | None = None,
) -> tuple[Tensor, dict[str, Tensor], list[Tensor]]:
    """`dqn_loss(...)` and the gradients of its loss w.r.t. online.parameters(), in that order
    (written into `out` when given, e.g. views from `grad_buffers`)."""
    online = online if isinstance(online, MLPFast) else MLPFast(online)
    target = target if target is None or isinstance(target, MLPFast) else MLPFast(target)
    n = batch.reward.shape[0]
    # One online pass over [obs; next_obs] when the targets need online(next_obs): one matmul
    # of 2N rows per layer instead of two of N, and half the per-op overhead.
    both = target is None or double
    x = torch.cat([batch.obs, batch.next_obs]) if both else batch.obs  # [2N or N, *obs_shape]
    q_all, saved = online.forward(x)  # [2N or N, A]
    if target is None:
        next_v = q_all[n:].amax(dim=1)  # [N]
    else:
        if target_q is None:
            target_q = target.forward(batch.next_obs)[0]  # [N, A]
        if double:
            best = q_all[n:].argmax(dim=1, keepdim=True)  # [N, 1]
            next_v = target_q.gather(1, best).squeeze(1)  # [N]
        else:
            next_v = target_q.amax(dim=1)  # [N]
    y = torch.addcmul(batch.reward, batch.discount, next_v)  # [N]
    action = batch.action.long().unsqueeze(1)  # [N, 1]
    if both:
        q_all = q_all[:n]  # [N, A]
    q = q_all.gather(1, action).squeeze(1)  # [N]
    td = q - y  # [N]
    w = batch.weight
    if loss == "mse":
        value = F.mse_loss(q, y, reduction="mean" if w is None else "none")
        dq = td * (2.0 / n)  # d mean((q - y)^2) / dq
    else:
        value = F.huber_loss(q, y, reduction="mean" if w is None else "none", delta=huber_delta)
        dq = td.clamp(-huber_delta, huber_delta).mul_(1.0 / n)
    if w is not None:
        value = (value * w).mean()
        dq.mul_(w)
    g = torch.zeros_like(q_all).scatter_(1, action, dq.unsqueeze(1))  # [N, A], d loss / d Q
    if out is None:
        out = online.new_grads()
    online.backward(g, saved, out, rows=n)
    return value, {"loss": value, "q": q, "td_error": td}, out
