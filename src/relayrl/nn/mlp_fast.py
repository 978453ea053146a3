"""The fast twins of mlp.py's forward + autograd: an inference path for actors and
hand-written gradients for learners, both on detached views of a network's parameters.

Why: on a CPU the networks RL uses are small, and per-op dispatch, autograd's bookkeeping
(graph nodes, AccumulateGrad, transposes, copies) and per-tensor clipping cost about as much
as the matmuls. The views share memory with the parameters, so they follow in-place updates
(optimizer steps, load_state_dict, weight pulls) and never go stale.

- `MLPInference`: [B, in] -> [B, out] NumPy array without a graph: NumPy matmuls for small
  batches (where torch's per-op dispatch dominates), torch.addmm with in-place activations
  for the rest.
- `MLPFast` / `TwinMLPFast`: a forward pass that keeps its activations and the backward pass
  written out with the kernels autograd calls, sharing one loop (`_Fast`); gradients equal
  autograd's up to float rounding (tests/test_nn.py checks every registered activation).
  The losses' own gradients live with their algorithms (agents/*/losses_fast.py).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from relayrl.nn.activations import ACTIVATIONS
from relayrl.nn.mlp import MLP, TwinMLP, linear_layers

Tensor = torch.Tensor

# Above this many multiply-adds per forward pass torch's CPU matmul (MKL's sgemm) beats NumPy's
# OpenBLAS; below it torch's per-op dispatch dominates (docs/benchmarks.md has the crossovers).
# OpenBLAS stays on one thread: its threads would spin on the core the envs step on.
NUMPY_MAX_MACS = 500_000


class MLPInference:
    """An actor's inference-only forward pass of a float32 MLP on the CPU: [B, in] tensor ->
    [B, out] NumPy array, equal to `net(obs)` up to float rounding."""

    def __init__(self, net: MLP) -> None:
        if any(p.device.type != "cpu" or p.dtype != torch.float32 for p in net.parameters()):
            raise ValueError("MLPInference needs a float32 MLP on the CPU")
        act = ACTIVATIONS[net.activation]
        layers = linear_layers(net)
        self._np_layers = [(layer.weight.detach().numpy().T, layer.bias.detach().numpy()) for layer in layers]
        self._np_act = act.numpy
        self.layers = [(layer.weight.detach().t(), layer.bias.detach()) for layer in layers]  # [in, out], [out]
        self._act_ = act.inplace
        self.max_rows = max(1, NUMPY_MAX_MACS // sum(w.size for w, _ in self._np_layers))

    def suits_numpy(self, rows: int) -> bool:
        """Whether a batch of `rows` is small enough for the NumPy path."""
        return rows <= self.max_rows

    def numpy(self, x: np.ndarray) -> np.ndarray:
        """The forward pass in NumPy: [B, *obs_shape] -> [B, out]."""
        if x.ndim != 2:
            x = x.reshape(x.shape[0], -1)  # [B, *obs_shape] -> [B, obs_dim]
        if x.dtype != np.float32:
            x = x.astype(np.float32)
        last = len(self._np_layers) - 1
        for i, (w_t, b) in enumerate(self._np_layers):
            x = x @ w_t + b  # [B, out]
            if i < last:
                x = self._np_act(x)
        return x

    def __call__(self, obs: Tensor) -> np.ndarray:
        if self.suits_numpy(obs.shape[0]):
            return self.numpy(obs.numpy())
        x = obs.reshape(obs.shape[0], -1) if obs.dim() != 2 else obs  # [B, *obs_shape] -> [B, obs_dim]
        if x.dtype != torch.float32:
            x = x.float()
        x = x.detach()  # no graph (the weights are detached views already)
        last = len(self.layers) - 1
        for i, (w_t, b) in enumerate(self.layers):
            x = torch.addmm(b, x, w_t)  # [B, out], one allocation per layer
            if i < last:
                x = self._act_(x)
        return x.numpy()


def supports(net: torch.nn.Module) -> bool:
    """Whether this network has hand-written gradients here (an MLP or TwinMLP, not a subclass)."""
    return type(net) in (MLP, TwinMLP) and net.activation in ACTIVATIONS


class Saved(NamedTuple):
    """What a forward pass keeps for its backward: every layer's input and, where the
    activation's backward needs it, every hidden pre-activation."""

    inputs: list[Tensor]
    pre: list[Tensor | None]


class _Fast:
    """The forward-that-saves and backward loop; subclasses give each layer's affine map,
    its parameter gradients and its input gradient."""

    def __init__(self, activation: str, layers: int) -> None:
        act = ACTIVATIONS[activation]
        self.activation = activation
        self._fwd = act.torch if act.needs_input else act.inplace
        self._back = act.backward
        self._keep_pre = act.needs_input
        self._last = layers - 1

    def _affine(self, i: int, x: Tensor) -> Tensor:
        raise NotImplementedError

    def _param_grads(self, i: int, g: Tensor, x: Tensor, out: list[Tensor]) -> None:
        raise NotImplementedError

    def _input_grad(self, i: int, g: Tensor) -> Tensor:
        raise NotImplementedError

    def forward(self, x: Tensor) -> tuple[Tensor, Saved]:
        """The output ([B, out]; a twin's Q [copies, N]) of x [B, *in_shape], and what `backward` needs."""
        if x.dim() != 2:
            x = x.reshape(x.shape[0], -1)  # [B, *obs_shape] -> [B, obs_dim]
        if x.dtype != torch.float32:
            x = x.float()
        fwd, keep_pre, last = self._fwd, self._keep_pre, self._last
        inputs: list[Tensor] = []
        pre: list[Tensor | None] = []
        for i in range(last + 1):
            inputs.append(x)
            x = self._affine(i, x)
            if i < last:
                pre.append(x if keep_pre else None)
                x = fwd(x)
        return x, Saved(inputs, pre)

    def backward(self, g: Tensor, saved: Saved, out: list[Tensor] | None, rows: int | None = None,
                 input_grad: bool = False) -> Tensor | None:
        """Parameter gradients from g = d loss / d output into `out` (None: skip them); returns
        d loss / d input [N, in] (a twin's summed over the copies) when `input_grad`. Only the
        first `rows` rows of an MLP's forward pass took part in the loss (None: all)."""
        back = self._back
        for i in range(self._last, -1, -1):
            x = saved.inputs[i]
            if rows is not None and x.shape[0] != rows:
                x = x[:rows]
            if out is not None:
                self._param_grads(i, g, x, out)
            if i == 0 and not input_grad:
                return None
            g = self._input_grad(i, g)
            if i > 0:
                z = saved.pre[i - 1]
                if z is not None and rows is not None and z.shape[0] != rows:
                    z = z[:rows]
                g = back(g, z, x)  # d loss / d pre-activation of layer i - 1
        return g


class MLPFast(_Fast):
    """An MLP's forward-that-saves and backward. Gradients come in net.parameters() order
    [W0, b0, W1, b1, ...], written into the tensors of `out` (e.g. views from `grad_buffers`)."""

    def __init__(self, net: MLP) -> None:
        super().__init__(net.activation, len(net.layers))
        layers = linear_layers(net)
        self.weight = [layer.weight.detach() for layer in layers]  # [out, in]
        self.weight_t = [w.t() for w in self.weight]  # [in, out]
        self.bias = [layer.bias.detach() for layer in layers]  # [out]

    def new_grads(self) -> list[Tensor]:
        return [torch.empty_like(t) for pair in zip(self.weight, self.bias, strict=True) for t in pair]

    def _affine(self, i: int, x: Tensor) -> Tensor:
        return torch.addmm(self.bias[i], x, self.weight_t[i])  # [B, out], what F.linear computes

    def _param_grads(self, i: int, g: Tensor, x: Tensor, out: list[Tensor]) -> None:
        torch.mm(g.t(), x, out=out[2 * i])  # [out, in]
        torch.sum(g, 0, out=out[2 * i + 1])  # [out]

    def _input_grad(self, i: int, g: Tensor) -> Tensor:
        return torch.mm(g, self.weight[i])  # [N, in]


class TwinMLPFast(_Fast):
    """A TwinMLP's forward-that-saves and backward: weights [copies, in, out]. Gradients come
    in net.parameters() order (every weight, then every bias) as new tensors put into `out`."""

    def __init__(self, net: TwinMLP) -> None:
        super().__init__(net.activation, len(net.weights))
        self.weight = [w.detach() for w in net.weights]  # [copies, in, out]
        self.weight_t = [w.transpose(1, 2) for w in self.weight]  # [copies, out, in]
        self.bias = [b.detach() for b in net.biases]  # [copies, 1, out]

    def new_grads(self) -> list[Tensor]:
        """A list for `backward` to fill (its entries are replaced, not written into)."""
        return [torch.empty(0)] * (2 * len(self.weight))

    def _affine(self, i: int, x: Tensor) -> Tensor:
        if i == self._last:  # the 1-wide head as multiply-and-sum, as TwinMLP.forward does
            return (x * self.weight_t[i]).sum(-1) + self.bias[i].squeeze(-1)  # [copies, N]
        if i == 0:  # x [N, in] broadcast to every copy (a stride-0 view): the bias in the GEMM
            copies = self.weight[0].shape[0]
            return torch.baddbmm(self.bias[0], x.expand(copies, *x.shape), self.weight[0])  # [copies, N, out]
        return torch.baddbmm(self.bias[i], x, self.weight[i])  # [copies, N, out]

    def _param_grads(self, i: int, g: Tensor, x: Tensor, out: list[Tensor]) -> None:
        n = len(self.weight)
        if i == self._last:
            x_t, g1 = x.transpose(-1, -2), g.unsqueeze(-1)  # [copies, h, N] ([h, N]: no hidden layer), [copies, N, 1]
            out[i] = torch.bmm(x_t, g1) if x.dim() == 3 else torch.matmul(x_t, g1)  # [copies, h, 1]
            out[n + i] = g.sum(1).view(-1, 1, 1)  # [copies, 1, 1]
        else:
            out[i] = torch.matmul(x.transpose(-1, -2), g)  # [copies, in, out] (layer 0: x [N, in])
            out[n + i] = g.sum(1, keepdim=True)  # [copies, 1, out]

    def _input_grad(self, i: int, g: Tensor) -> Tensor:
        if i == self._last:
            g = g.unsqueeze(-1) * self.weight_t[i]  # [copies, N, h]
        else:
            g = torch.bmm(g, self.weight_t[i])  # [copies, N, in]
        return g.sum(0) if i == 0 else g


def grad_buffers(net: torch.nn.Module) -> tuple[Tensor, list[Tensor]]:
    """One flat zero buffer and views of it shaped like net.parameters(), in that order."""
    params = list(net.parameters())
    flat = torch.zeros(sum(p.numel() for p in params), device=params[0].device)
    views, start = [], 0
    for p in params:
        views.append(flat[start:start + p.numel()].view_as(p))
        start += p.numel()
    return flat, views


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


@torch.no_grad()
def clip_grad_norm_(grads: list[Tensor], max_norm: float) -> Tensor:
    """torch.nn.utils.clip_grad_norm_'s rule on plain gradient tensors (no .grad needed)."""
    total = torch.linalg.vector_norm(torch.stack(torch._foreach_norm(grads)))
    torch._foreach_mul_(grads, torch.clamp(max_norm / (total + 1e-6), max=1.0))
    return total
