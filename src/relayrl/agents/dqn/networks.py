"""The Q-network for discrete actions, built from specs: an MLP, or a conv net for frames."""

from __future__ import annotations

from torch import nn

from relayrl.agents.dqn.config import DQNConfig
from relayrl.errors import UserError
from relayrl.nn import CONV_NETWORKS, MLP, ConvQNet, tf_agents_init_
from relayrl.specs import DiscreteSpec, Spec, flat_dim


def q_network(obs_spec: Spec, action_spec: Spec, cfg: DQNConfig) -> nn.Module:
    if not isinstance(action_spec, DiscreteSpec):
        raise UserError("DQN needs a discrete action space (gymnasium.spaces.Discrete); "
                        "use SAC for continuous actions")
    if cfg.network in CONV_NETWORKS:
        if len(obs_spec.shape) != 3:
            raise UserError(f"agent.network={cfg.network!r} needs image observations [C, H, W] (e.g. relayrl/"
                            f"Atari-Pong-v0's [4, 84, 84]), got {list(obs_spec.shape)}; use agent.network='mlp'")
        try:
            return ConvQNet(tuple(obs_spec.shape), action_spec.n)
        except RuntimeError:  # a conv kernel larger than its input
            raise UserError(f"agent.network={cfg.network!r} needs frames of at least 36x36, "
                            f"got {list(obs_spec.shape)}") from None
    net = MLP(flat_dim(obs_spec), list(cfg.hidden), action_spec.n, cfg.activation)
    if cfg.init == "tf-agents":
        tf_agents_init_(net)
    return net
