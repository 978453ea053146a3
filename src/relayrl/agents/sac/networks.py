"""SAC networks: a tanh-Gaussian actor (an MLP with mean and log-std heads) and twin critics
that run as one batched network."""

from __future__ import annotations

import contextlib

import numpy as np
import torch
from torch import nn

from relayrl.errors import UserError
from relayrl.nn import TwinMLP
from relayrl.nn.encoders import encoded_mlp, encoder_dim, make_encoder
from relayrl.specs import ArraySpec, Spec, describe, flat_dim, is_bounded_box, which_algorithms


def check_action_spec(action_spec: Spec) -> ArraySpec:
    if not is_bounded_box(action_spec):
        raise UserError("SAC takes a Box action space of floats with finite low and high; this env's action space "
                        f"is {describe(action_spec)} ({which_algorithms(action_spec)})")
    assert isinstance(action_spec, ArraySpec)
    fixed = np.flatnonzero(np.asarray(action_spec.high) <= np.asarray(action_spec.low))
    if fixed.size:
        # Its entropy term and the critics' action inputs would count a dimension that cannot vary.
        raise UserError(f"SAC needs low < high in every action dimension; this env's action space "
                        f"{describe(action_spec)} has low == high at flat index {', '.join(map(str, fixed))}: "
                        "leave that dimension out of the space (a wrapper that adds its one value), or use PPO")
    return action_spec


def actor_network(obs_spec: Spec, action_spec: ArraySpec, hidden: list[int], activation: str,
                  encoder: str = "auto") -> nn.Module:
    """obs -> [mean, log_std] of the pre-tanh Gaussian: out dim 2 * |A|."""
    return encoded_mlp(obs_spec, encoder, list(hidden), 2 * flat_dim(action_spec), activation)


class EncodedTwin(nn.Module):
    """The twin critics behind an observation encoder of their own (SB3's off-policy default:
    actor and critics do not share one)."""

    def __init__(self, encoder: nn.Module, twin: TwinMLP) -> None:
        super().__init__()
        self.encoder = encoder
        self.twin = twin

    def forward(self, obs: torch.Tensor, action: torch.Tensor, detach_params: bool = False) -> torch.Tensor:
        with torch.no_grad() if detach_params else contextlib.nullcontext():  # the actor's loss needs dQ/da only
            features = self.encoder(obs)
        return self.twin(features, action, detach_params)


def critic_network(obs_spec: Spec, action_spec: ArraySpec, hidden: list[int], activation: str,
                   encoder: str = "auto") -> nn.Module:
    """Twin Q(s, a) critics as one batched network: [obs, action] -> Q [2, N]."""
    enc = make_encoder(obs_spec, encoder)
    if enc is None:
        return TwinMLP(flat_dim(obs_spec) + flat_dim(action_spec), list(hidden), activation)
    return EncodedTwin(enc, TwinMLP(encoder_dim(enc) + flat_dim(action_spec), list(hidden), activation))
