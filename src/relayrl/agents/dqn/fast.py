"""The DQN loss and its gradients for MLP Q-networks, computed by hand instead of by autograd.

Why: on a CPU a (256, 256) update is a handful of [64, 256] x [256, 256] matmuls plus ~100
small ops, and autograd's bookkeeping (graph nodes, AccumulateGrad, transposes, copies) and
the per-tensor clipping ops cost about as much as the matmuls (BENCHMARKS.md, "Where the time
of a DQN iteration goes"). Here the forward pass keeps its activations and the backward pass
is the chain rule written out with the kernels autograd calls (addmm, mm, threshold/tanh/elu
backward), writing into one flat gradient buffer, so clipping is one norm and one multiply.
Gradients equal autograd's up to float rounding: tests/test_dqn_fast.py checks them against
`dqn_loss` + `backward()` for every activation, both losses, with weights and with clipping.

`dqn_loss_and_grads` is pure like `dqn_loss`: same inputs, same (loss, metrics), plus the
gradients; `out` only says where to write them.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F

from relayrl.networks import MLP
from relayrl.types import Batch

Tensor = torch.Tensor

# The activation in place where the backward formula needs only its output, as autograd's do.
_FORWARD: dict[str, Callable[[Tensor], Tensor]] = {"relu": torch.relu_, "tanh": torch.tanh_, "elu": F.elu}
_aten = torch.ops.aten
# d loss / d z from d loss / d h, given z (pre-activation, kept for elu only) and h = act(z).
_BACKWARD: dict[str, Callable[[Tensor, Tensor | None, Tensor], Tensor]] = {
    "relu": lambda g, z, h: _aten.threshold_backward.default(g, h, 0),
    "tanh": lambda g, z, h: _aten.tanh_backward.default(g, h),
    "elu": lambda g, z, h: _aten.elu_backward.default(g, 1.0, 1, 1, False, z),
}


def supports(net: torch.nn.Module) -> bool:
    """Whether `dqn_loss_and_grads` handles this network."""
    return type(net) is MLP and net.activation in _BACKWARD


class MLPView:
    """Detached views of an MLP's parameters, built once: they follow in-place updates
    (optimizer steps, load_state_dict) and save the per-call detach/transpose ops."""

    def __init__(self, net: MLP) -> None:
        self.activation = net.activation
        self.weight = [layer.weight.detach() for layer in net.layers]  # [out, in]
        self.weight_t = [w.t() for w in self.weight]  # [in, out]
        self.bias = [layer.bias.detach() for layer in net.layers]  # [out]

    def forward(self, x: Tensor) -> tuple[Tensor, list[Tensor], list[Tensor | None]]:
        """Output [B, out], the input of every layer, and the pre-activations elu needs."""
        if x.dim() != 2:
            x = x.reshape(x.shape[0], -1)  # [B, *obs_shape] -> [B, obs_dim]
        if x.dtype != torch.float32:
            x = x.float()
        act, keep_pre = _FORWARD[self.activation], self.activation == "elu"
        inputs: list[Tensor] = []
        pre: list[Tensor | None] = []
        last = len(self.weight) - 1
        for i, (w_t, b) in enumerate(zip(self.weight_t, self.bias, strict=True)):
            inputs.append(x)
            x = torch.addmm(b, x, w_t)  # [B, out], what F.linear computes
            if i < last:
                pre.append(x if keep_pre else None)
                x = act(x)
        return x, inputs, pre

    def backward(self, g: Tensor, inputs: list[Tensor], pre: list[Tensor | None], rows: int,
                 out: list[Tensor]) -> None:
        """Writes d loss / d [W0, b0, W1, b1, ...] into `out` from g = d loss / d output [N, out].

        Only the first `rows` rows of the saved activations took part in the loss.
        """
        back = _BACKWARD[self.activation]
        for i in range(len(self.weight) - 1, -1, -1):
            x = inputs[i]
            if x.shape[0] != rows:
                x = x[:rows]  # [N, in]
            torch.mm(g.t(), x, out=out[2 * i])  # [out, in]
            torch.sum(g, 0, out=out[2 * i + 1])  # [out]
            if i > 0:
                z = pre[i - 1]
                if z is not None and z.shape[0] != rows:
                    z = z[:rows]
                g = back(torch.mm(g, self.weight[i]), z, x)  # [N, in]


def grad_buffers(net: MLP) -> tuple[Tensor, list[Tensor]]:
    """One flat zero buffer and views of it shaped like net.parameters(), in that order."""
    params = list(net.parameters())
    flat = torch.zeros(sum(p.numel() for p in params), device=params[0].device)
    views, start = [], 0
    for p in params:
        views.append(flat[start:start + p.numel()].view_as(p))
        start += p.numel()
    return flat, views


@torch.no_grad()
def dqn_loss_and_grads(
    online: MLP | MLPView,
    target: MLP | MLPView | None,
    batch: Batch,
    *,
    double: bool,
    loss: str = "huber",
    huber_delta: float = 1.0,
    out: list[Tensor] | None = None,
) -> tuple[Tensor, dict[str, Tensor], list[Tensor]]:
    """`dqn_loss(...)` and the gradients of its loss w.r.t. online.parameters(), in that order
    (written into `out` when given, e.g. views from `grad_buffers`)."""
    online = online if isinstance(online, MLPView) else MLPView(online)
    target = target if target is None or isinstance(target, MLPView) else MLPView(target)
    n = batch.reward.shape[0]
    # One online pass over [obs; next_obs] when the targets need online(next_obs): one matmul
    # of 2N rows per layer instead of two of N, and half the per-op overhead.
    both = target is None or double
    x = torch.cat([batch.obs, batch.next_obs]) if both else batch.obs  # [2N or N, *obs_shape]
    q_all, inputs, pre = online.forward(x)  # [2N or N, A]
    if target is None:
        next_v = q_all[n:].amax(dim=1)  # [N]
    else:
        target_q = batch.target_q if batch.target_q is not None else target.forward(batch.next_obs)[0]  # [N, A]
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
        out = [torch.empty_like(t) for pair in zip(online.weight, online.bias, strict=True) for t in pair]
    online.backward(g, inputs, pre, n, out)
    return value, {"loss": value, "q": q, "td_error": td}, out


@torch.no_grad()
def clip_flat_grad_norm_(flat: Tensor, max_norm: float) -> Tensor:
    """torch.nn.utils.clip_grad_norm_ for gradients that live in one flat buffer.

    Same rule (scale by min(max_norm / (norm + 1e-6), 1)); one norm instead of one per
    tensor, so the norm may differ from torch's in the last bit.
    """
    total = torch.linalg.vector_norm(flat)
    if flat.device.type == "cpu":
        coef = max_norm / (total.item() + 1e-6)  # a CPU scalar costs no sync
        if coef < 1.0:
            flat.mul_(coef)
    else:
        flat.mul_(torch.clamp(max_norm / (total + 1e-6), max=1.0))
    return total
