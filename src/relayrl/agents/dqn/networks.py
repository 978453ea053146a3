"""The Q-network for discrete actions, built from specs: an MLP behind the observations'
encoder, or the conv Q-network of the pixel presets (`agent.network`)."""

from __future__ import annotations

from torch import nn

from relayrl.agents.dqn.config import DQNConfig
from relayrl.errors import UserError
from relayrl.nn import CONV_NETWORKS, ConvQNet, tf_agents_init_
from relayrl.nn.encoders import Encoded, encoded_mlp
from relayrl.specs import ArraySpec, DiscreteSpec, Spec, describe, image_layout, is_image


def q_network(obs_spec: Spec, action_spec: Spec, cfg: DQNConfig) -> nn.Module:
    if not isinstance(action_spec, DiscreteSpec):
        raise UserError(f"DQN takes a Discrete action space; this env's action space is {describe(action_spec)} "
                        "(use SAC or PPO for Box actions, PPO for MultiDiscrete and MultiBinary)")
    if cfg.network in CONV_NETWORKS:
        # the Atari presets' network: stacked frames channels first, as relayrl/Atari-Pong-v0 gives them
        instead = "use agent.network='mlp' with agent.encoder='auto' or 'nature_cnn', which take any image layout"
        if not (isinstance(obs_spec, ArraySpec) and is_image(obs_spec) and len(obs_spec.shape) == 3
                and not image_layout(obs_spec)[1]):
            raise UserError(f"agent.network={cfg.network!r} needs uint8 frames [C, H, W], channels first (as "
                            f"relayrl/Atari-Pong-v0's [4, 84, 84]); this env's observations are {describe(obs_spec)}: "
                            + instead)
        try:
            return ConvQNet(tuple(obs_spec.shape), action_spec.n)
        except RuntimeError:  # a conv kernel larger than its input
            raise UserError(f"agent.network={cfg.network!r} needs frames of at least 36x36, got "
                            f"{describe(obs_spec)}: {instead}") from None
    net = encoded_mlp(obs_spec, cfg.encoder, list(cfg.hidden), action_spec.n, cfg.activation)
    if cfg.init == "tf-agents":
        tf_agents_init_(net.head if isinstance(net, Encoded) else net)
    return net
