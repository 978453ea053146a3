"""The Q-network for discrete actions, built from specs: an MLP behind the observations'
encoder, or the conv Q-network of the pixel presets (`agent.network`)."""

from __future__ import annotations

from torch import nn

from relayrl.agents.dqn.config import DQNConfig
from relayrl.errors import UserError
from relayrl.nn import CONV_NETWORKS, ConvQNet, tf_agents_init_
from relayrl.nn.encoders import Encoded, encoded_mlp
from relayrl.specs import DiscreteSpec, Spec, describe


def q_network(obs_spec: Spec, action_spec: Spec, cfg: DQNConfig) -> nn.Module:
    if not isinstance(action_spec, DiscreteSpec):
        raise UserError(f"DQN takes a Discrete action space; this env's action space is {describe(action_spec)} "
                        "(use SAC or PPO for Box actions, PPO for MultiDiscrete and MultiBinary)")
    if cfg.network in CONV_NETWORKS:
        if len(obs_spec.shape) != 3:
            raise UserError(f"agent.network={cfg.network!r} needs image observations [C, H, W] (e.g. relayrl/"
                            f"Atari-Pong-v0's [4, 84, 84]), got {list(obs_spec.shape)}; use agent.network='mlp'")
        try:
            return ConvQNet(tuple(obs_spec.shape), action_spec.n)
        except RuntimeError:  # a conv kernel larger than its input
            raise UserError(f"agent.network={cfg.network!r} needs frames of at least 36x36, "
                            f"got {list(obs_spec.shape)}") from None
    net = encoded_mlp(obs_spec, cfg.encoder, list(cfg.hidden), action_spec.n, cfg.activation)
    if cfg.init == "tf-agents":
        tf_agents_init_(net.head if isinstance(net, Encoded) else net)
    return net
