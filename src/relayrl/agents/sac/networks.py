"""SAC networks: a tanh-Gaussian actor (an MLP with mean and log-std heads) and twin critics
that run as one batched network."""

from __future__ import annotations

from relayrl.errors import UserError
from relayrl.nn import MLP, TwinMLP
from relayrl.specs import ArraySpec, Spec, flat_dim, is_bounded_box


def check_action_spec(action_spec: Spec) -> ArraySpec:
    if not is_bounded_box(action_spec):
        raise UserError("SAC needs a bounded continuous action space (gymnasium.spaces.Box with finite "
                        "low/high); use DQN for discrete actions")
    assert isinstance(action_spec, ArraySpec)
    return action_spec


def actor_network(obs_spec: Spec, action_spec: ArraySpec, hidden: list[int], activation: str) -> MLP:
    """obs -> [mean, log_std] of the pre-tanh Gaussian: out dim 2 * |A|."""
    return MLP(flat_dim(obs_spec), list(hidden), 2 * flat_dim(action_spec), activation)


def critic_network(obs_spec: Spec, action_spec: ArraySpec, hidden: list[int], activation: str) -> TwinMLP:
    """Twin Q(s, a) critics as one batched network: [obs, action] -> Q [2, N]."""
    return TwinMLP(flat_dim(obs_spec) + flat_dim(action_spec), list(hidden), activation)
