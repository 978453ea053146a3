"""SAC networks: a tanh-Gaussian actor (an MLP with mean and log-std heads) and twin critics
that run as one batched network."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from relayrl.errors import UserError
from relayrl.networks import ACTIVATIONS, MLP
from relayrl.specs import ArraySpec, Spec, flat_dim


def check_action_spec(action_spec: Spec) -> ArraySpec:
    bounded = (isinstance(action_spec, ArraySpec) and action_spec.dtype.is_floating_point
               and action_spec.low is not None and action_spec.high is not None
               and bool(np.isfinite(action_spec.low).all() and np.isfinite(action_spec.high).all()))
    if not bounded:
        raise UserError("SAC needs a bounded continuous action space (gymnasium.spaces.Box with finite "
                        "low/high); use DQN for discrete actions")
    assert isinstance(action_spec, ArraySpec)
    return action_spec


def actor_network(obs_spec: Spec, action_spec: ArraySpec, hidden: list[int], activation: str) -> MLP:
    """obs -> [mean, log_std] of the pre-tanh Gaussian: out dim 2 * |A|."""
    return MLP(flat_dim(obs_spec), list(hidden), 2 * flat_dim(action_spec), activation)


class TwinCritic(nn.Module):
    """Two Q(s, a) MLPs evaluated together: each layer is one batched matmul over [2, N, *].

    Weights are [2, in, out]; the first layer broadcasts the shared input to both critics.
    One baddbmm per layer replaces two addmm calls and halves the autograd nodes. Init as
    nn.Linear's: U(-1/sqrt(in), 1/sqrt(in)) for weights and biases.
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
        self._act = ACTIVATIONS[activation]
        # ParameterList indexing and iteration cost ~35 us per forward pass in Python; a
        # plain list of the same Parameter objects (so state_dict loads and deepcopy agree).
        self._layers = list(zip(self.weights, self.biases, strict=True))

    def _apply(self, fn, recurse=True):  # type: ignore[no-untyped-def]
        out = super()._apply(fn, recurse)
        self._layers = list(zip(self.weights, self.biases, strict=True))  # in case .to() made new Parameters
        return out

    def forward(self, obs: torch.Tensor, action: torch.Tensor, detach_params: bool = False) -> torch.Tensor:
        """Q-values [2, N]. `detach_params`: gradients flow to the inputs only (the actor loss
        needs dQ/da, not dQ/dtheta, which would be a third of the work wasted)."""
        x = torch.cat([obs.reshape(obs.shape[0], -1).float(), action], dim=-1)  # [N, in]
        last = len(self._layers) - 1
        for i, (w, b) in enumerate(self._layers):
            if detach_params:
                w, b = w.detach(), b.detach()
            if i == last:
                # The 1-wide head as multiply-and-sum: a [2, N, h] x [2, h, 1] bmm is a
                # degenerate GEMM that costs ~150 us on this CPU forward and ~300 us backward,
                # against ~30 us for the elementwise form.
                return (x * w.transpose(1, 2)).sum(-1) + b.squeeze(-1)  # [2, N]
            x = torch.baddbmm(b, x, w) if x.dim() == 3 else torch.matmul(x, w) + b  # [2, N, out]
            x = self._act(x)
        raise AssertionError("unreachable: the last layer returns")


def critic_network(obs_spec: Spec, action_spec: ArraySpec, hidden: list[int], activation: str) -> TwinCritic:
    return TwinCritic(flat_dim(obs_spec) + flat_dim(action_spec), list(hidden), activation)
