"""The MLP and the twin MLP (two MLPs run as one batched network), and TF-Agents' init.

Both call the matmul kernels directly instead of through nn.Linear modules: on a CPU the
module call's hook machinery costs more per layer than the matmul of a small net. Their
activations come from the one registry (activations.py); mlp_fast.py holds their
inference path and hand-written gradients.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import cast

import torch
import torch.nn.functional as F
from torch import nn

from relayrl.nn.activations import ACTIVATIONS


class MLP(nn.Module):
    """in_dim -> hidden... -> out_dim with an activation between layers, none after the last.

    Parameters live in `layers` (plain nn.Linear), so state_dicts look as usual.
    """

    def __init__(self, in_dim: int, hidden: list[int], out_dim: int, activation: str = "relu") -> None:
        super().__init__()
        sizes = [in_dim, *hidden, out_dim]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:], strict=False))
        self.activation = activation
        self._act = ACTIVATIONS[activation].torch

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dim() != 2:
            x = x.reshape(x.shape[0], -1)  # [B, *obs_shape] -> [B, obs_dim]
        layers = linear_layers(self)
        if x.dtype != torch.float32:
            x = x.to(layers[0].weight.dtype)  # observations in the network's dtype (float32 unless .double())
        last = len(layers) - 1
        for i, layer in enumerate(layers):
            x = F.linear(x, layer.weight, layer.bias)
            if i < last:
                x = self._act(x)
        return x


def linear_layers(net: MLP) -> Sequence[nn.Linear]:
    """`net.layers` as the nn.Linear layers they are (ModuleList types its items as Module)."""
    return cast("Sequence[nn.Linear]", net.layers)


class TwinMLP(nn.Module):
    """`copies` MLPs with one output each (twin Q-critics), evaluated together: each layer is
    one batched matmul over [copies, N, *].

    Weights are [copies, in, out], biases [copies, 1, out]; the first layer broadcasts the
    shared input to every copy. One baddbmm per layer replaces `copies` addmm calls and
    divides the autograd nodes as much. Init as nn.Linear's: U(-1/sqrt(in), 1/sqrt(in)).
    """

    def __init__(self, in_dim: int, hidden: list[int], activation: str = "relu", copies: int = 2) -> None:
        super().__init__()
        sizes = [in_dim, *hidden, 1]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for a, b in zip(sizes[:-1], sizes[1:], strict=False):
            bound = 1.0 / math.sqrt(a)
            self.weights.append(nn.Parameter(torch.empty(copies, a, b).uniform_(-bound, bound)))
            self.biases.append(nn.Parameter(torch.empty(copies, 1, b).uniform_(-bound, bound)))
        self.activation = activation
        self._act = ACTIVATIONS[activation].torch
        # ParameterList indexing and iteration run in Python on every call; a plain list of
        # the same Parameter objects (so state_dict loads and deepcopy agree) does not.
        self._layers = list(zip(self.weights, self.biases, strict=True))

    def _apply(self, fn, recurse=True):  # type: ignore[no-untyped-def]
        out = super()._apply(fn, recurse)
        self._layers = list(zip(self.weights, self.biases, strict=True))  # in case .to() made new Parameters
        return out

    def forward(self, obs: torch.Tensor, action: torch.Tensor, detach_params: bool = False) -> torch.Tensor:
        """Q-values [copies, N] of [obs, action]. `detach_params`: gradients flow to the inputs
        only (the actor loss needs dQ/da, not dQ/dtheta, which would be a third of the work)."""
        x = torch.cat([obs.reshape(obs.shape[0], -1).float(), action], dim=-1)  # [N, in]
        last = len(self._layers) - 1
        for i, (w, b) in enumerate(self._layers):
            if detach_params:
                w, b = w.detach(), b.detach()
            if i == last:
                # The 1-wide head as multiply-and-sum: a [copies, N, h] x [copies, h, 1] bmm is a
                # degenerate GEMM, several times slower on CPU than the elementwise form.
                return (x * w.transpose(1, 2)).sum(-1) + b.squeeze(-1)  # [copies, N]
            x = torch.baddbmm(b, x, w) if x.dim() == 3 else torch.matmul(x, w) + b  # [copies, N, out]
            x = self._act(x)
        raise AssertionError("unreachable: the last layer returns")


def tf_agents_init_(net: MLP) -> None:
    """TF-Agents' QNetwork init, as in its DQN tutorial.

    Hidden: VarianceScaling(scale=2, fan_in, truncated normal), zero bias. Head: uniform
    (-0.03, 0.03) weights and bias -0.2, so initial Q-values start small and equal.
    """
    layers = list(linear_layers(net))
    for layer in layers[:-1]:
        # Keras truncates at 2 std and divides std by 0.8796 to keep the variance.
        std = math.sqrt(2.0 / layer.in_features) / 0.87962566103423978
        nn.init.trunc_normal_(layer.weight, std=std, a=-2 * std, b=2 * std)
        nn.init.zeros_(layer.bias)
    nn.init.uniform_(layers[-1].weight, -0.03, 0.03)
    nn.init.constant_(layers[-1].bias, -0.2)
