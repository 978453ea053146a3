"""PPO's networks: the actor (logits, or a Gaussian mean with a state-independent log std)
and the critic, as two MLPs or as one whose last layer holds both heads, orthogonally
initialised (SB3 / CleanRL: gain sqrt(2) hidden, 0.01 policy head, 1 value head, zero bias),
relayrl's own encoders' layers too (gain sqrt(2), as SB3's features extractor; a user's encoder
keeps its own initialisation).
With observation normalisation, both see the observations through the actor's `ObsNorm`."""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import nn

from relayrl.agents.ppo.normalize import ObsNorm
from relayrl.errors import UserError
from relayrl.nn import MLP
from relayrl.nn.encoders import UserEncoder, encoder_dim, make_encoder
from relayrl.nn.mlp import linear_layers
from relayrl.specs import (
    ArraySpec,
    DiscreteSpec,
    MultiBinarySpec,
    MultiDiscreteSpec,
    Spec,
    describe,
    flat_dim,
    which_algorithms,
)


class ActionHead(NamedTuple):
    """What the policy's outputs parameterise for an action space."""

    outputs: int  # logits or Gaussian means
    discrete: bool  # logits (no log std)
    nvec: tuple[int, ...] = ()  # MultiDiscrete: the logits' block sizes
    binary: bool = False  # MultiBinary: Bernoulli logits
    shape: tuple[int, ...] = ()  # one action's shape (MultiDiscrete / MultiBinary)


def action_head(action_spec: Spec) -> ActionHead:
    """Logits of a Discrete, MultiDiscrete or MultiBinary space, or the mean of a Box's Gaussian."""
    if isinstance(action_spec, DiscreteSpec):
        return ActionHead(action_spec.n, True)
    if isinstance(action_spec, MultiDiscreteSpec):
        return ActionHead(sum(action_spec.nvec), True, action_spec.nvec, shape=action_spec.shape)
    if isinstance(action_spec, MultiBinarySpec):
        return ActionHead(flat_dim(action_spec), True, binary=True, shape=action_spec.shape)
    # A Box's bounds may be infinite (Stable-Baselines3 takes those too): the Gaussian sample is
    # clipped to them, which leaves an unbounded dimension as sampled; tanh squashing needs them finite.
    if (type(action_spec) is not ArraySpec or not action_spec.dtype.is_floating_point
            or action_spec.low is None or action_spec.high is None):
        raise UserError("PPO takes Discrete, MultiDiscrete, MultiBinary or Box (floats) action spaces; this "
                        f"env's action space is {describe(action_spec)} ({which_algorithms(action_spec)})")
    return ActionHead(flat_dim(action_spec), False)


def orthogonal_init_(net: MLP, head_gains: list[tuple[int, int, float]]) -> None:
    """Hidden layers: orthogonal, gain sqrt(2); the last layer's rows [a, b) get their gain."""
    layers = list(linear_layers(net))
    for layer in layers[:-1]:
        nn.init.orthogonal_(layer.weight, math.sqrt(2.0))
        nn.init.zeros_(layer.bias)
    head = layers[-1]
    with torch.no_grad():
        for a, b, gain in head_gains:
            rows = torch.empty(b - a, head.in_features)
            nn.init.orthogonal_(rows, gain)
            head.weight[a:b] = rows
        head.bias.zero_()


def orthogonal_encoder_init_(encoder: nn.Module) -> None:
    """relayrl's encoders (conv nets, their Dict / Tuple combinations): every conv and linear
    layer orthogonal with gain sqrt(2), zero bias."""
    for m in encoder.modules():
        if isinstance(m, (nn.Conv2d, nn.Linear)):
            nn.init.orthogonal_(m.weight, math.sqrt(2.0))
            if m.bias is not None:
                nn.init.zeros_(m.bias)


class PolicyNet(nn.Module):
    """obs -> the policy's outputs [N, A] (logits or Gaussian mean); `log_std` [A] for
    continuous actions. With `shared`, `mlp` has one more output, the value, which `forward`
    leaves out: this module is what the actor's copy of the policy holds and pulls, the
    observation statistics (`obs_norm`'s buffers) and encoder included. The critic takes the
    same features (SB3's on-policy default: one encoder for both)."""

    def __init__(self, obs_spec: Spec, hidden: list[int], out: int, activation: str, shared: bool,
                 log_std_init: float | None, normalize_obs: bool = False, encoder: str = "auto") -> None:
        super().__init__()
        self.out = out
        self.encoder = make_encoder(obs_spec, encoder)
        if self.encoder is not None and normalize_obs:
            raise UserError(f"agent.normalize_obs=true normalises observations the MLP takes as they are; this env's "
                            f"{describe(obs_spec)} goes through an encoder ({type(self.encoder).__name__}) "
                            "first: set agent.normalize_obs=false")
        if self.encoder is not None and not isinstance(self.encoder, UserEncoder):
            orthogonal_encoder_init_(self.encoder)
        self.features_dim = flat_dim(obs_spec) if self.encoder is None else encoder_dim(self.encoder)
        self.obs_norm = ObsNorm(self.features_dim) if normalize_obs else None
        self.mlp = MLP(self.features_dim, list(hidden), out + int(shared), activation)
        gains = [(0, out, 0.01)] + ([(out, out + 1, 1.0)] if shared else [])
        orthogonal_init_(self.mlp, gains)
        self.log_std = None if log_std_init is None else nn.Parameter(torch.full((out,), float(log_std_init)))

    def features(self, obs: torch.Tensor) -> torch.Tensor:
        """What the MLPs take: the observations encoded, or normalised when the run normalises them."""
        if self.encoder is not None:
            return self.encoder(obs)
        return obs if self.obs_norm is None else self.obs_norm(obs)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.mlp(self.features(obs))[:, : self.out]


class PPONetworks(nn.Module):
    def __init__(self, obs_spec: Spec, action_spec: Spec, hidden: list[int], activation: str, shared: bool,
                 log_std_init: float, normalize_obs: bool = False, encoder: str = "auto") -> None:
        super().__init__()
        self.head = action_head(action_spec)
        self.discrete = self.head.discrete
        out = self.head.outputs
        self.policy = PolicyNet(obs_spec, hidden, out, activation, shared,
                                None if self.discrete else log_std_init, normalize_obs, encoder)
        self.critic: MLP | None = None
        if not shared:
            self.critic = MLP(self.policy.features_dim, list(hidden), 1, activation)
            orthogonal_init_(self.critic, [(0, 1, 1.0)])

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(policy outputs [N, A], values [N]) in one pass through a shared network."""
        x = self.policy.features(obs)
        if self.critic is None:
            both = self.policy.mlp(x)
            return both[:, : self.policy.out], both[:, self.policy.out]
        return self.policy.mlp(x)[:, : self.policy.out], self.critic(x)[:, 0]

    def saved_head(self) -> dict[str, torch.Tensor]:
        """The actor as a plain MLP's state_dict with outputs [A] (a shared net's value row cut),
        behind its encoder's (keys `encoder.*` and `head.*`, as `nn.encoders.Encoded`) where it has one."""
        out = self.policy.out
        mlp = {k: (v[:out] if k.startswith(f"layers.{len(self.policy.mlp.layers) - 1}.") else v).detach().cpu()
               .clone() for k, v in self.policy.mlp.state_dict().items()}
        if self.policy.encoder is None:
            return mlp
        enc = {f"encoder.{k}": v.detach().cpu().clone() for k, v in self.policy.encoder.state_dict().items()}
        return {**enc, **{f"head.{k}": v for k, v in mlp.items()}}
