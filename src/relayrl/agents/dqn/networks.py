"""The Q-network for discrete actions, built from specs: an MLP behind the observations'
encoder; the pixel presets' `agent.network` is the Nature CNN encoder with a linear head."""

from __future__ import annotations

from typing import Any

from torch import nn

from relayrl.agents.dqn.config import DQNConfig
from relayrl.errors import UserError
from relayrl.frames import image_layout, image_size
from relayrl.nn import tf_agents_init_
from relayrl.nn.encoders import NATURE_MIN_SIDE, Encoded, encoded_mlp
from relayrl.specs import (
    ArraySpec,
    DiscreteSpec,
    PackedSpec,
    Spec,
    describe,
    is_image,
    which_algorithms,
)


def q_network(obs_spec: Spec, action_spec: Spec, cfg: DQNConfig) -> nn.Module:
    if not isinstance(action_spec, DiscreteSpec):
        raise UserError(f"DQN takes a Discrete action space; this env's action space is {describe(action_spec)} "
                        f"({which_algorithms(action_spec)})")
    if cfg.network != "mlp":  # the Atari presets' net (q_layout)
        leaves = [f.spec for f in obs_spec.fields] if isinstance(obs_spec, PackedSpec) else [obs_spec]
        images = [s for s in leaves if isinstance(s, ArraySpec) and is_image(s)]  # a Dict's frames too
        # the encoder that does take these frames: the Nature CNN's strides need sides >= NATURE_MIN_SIDE
        cnn = "small_cnn" if any(min(image_size(s)) < NATURE_MIN_SIDE for s in images) else "nature_cnn"
        instead = (f"use agent.network='mlp' with agent.encoder='auto' or '{cnn}', which take any image layout"
                   if images else "use agent.network='mlp' (the default) for observations that are not frames")
        frames = obs_spec if isinstance(obs_spec, ArraySpec) and images else None
        if frames is None or len(frames.shape) != 3 or image_layout(frames)[1]:
            raise UserError(f"agent.network={cfg.network!r} needs uint8 frames [C, H, W], channels first (as "
                            f"relayrl/Atari-Pong-v0's [4, 84, 84]); this env's observations are {describe(obs_spec)}: "
                            + instead)
        if cnn == "small_cnn":
            raise UserError(f"agent.network={cfg.network!r} needs frames of at least {NATURE_MIN_SIDE}x"
                            f"{NATURE_MIN_SIDE}, got {describe(obs_spec)}: {instead}")
    encoder, hidden, activation = q_layout(cfg)
    net = encoded_mlp(obs_spec, encoder, hidden, action_spec.n, activation)
    if cfg.init == "tf-agents" and cfg.network == "mlp":  # agent.init is the MLP's; the conv net keeps torch's
        tf_agents_init_(net.head if isinstance(net, Encoded) else net)
    return net


def q_layout(cfg: DQNConfig) -> tuple[str, list[int], str]:
    """(encoder, hidden sizes, activation) of the Q-network: the Atari presets' `agent.network` is
    the Nature CNN encoder with one linear layer on its 512 features."""
    return (cfg.encoder, list(cfg.hidden), cfg.activation) if cfg.network == "mlp" else ("nature_cnn", [], "relu")


def conv_state_dict(state_dict: dict[str, Any]) -> dict[str, Any]:
    """A conv Q-network's state dict in the keys of `q_network`'s modules: policy files with
    `"network"` and checkpoints of such runs may hold it as convs.*, head.0.*, head.2.*."""
    renames = (("convs.", "encoder.convs."), ("head.0.", "encoder.dense.0."), ("head.2.", "head.layers.0."))
    out = {}
    for key, value in state_dict.items():
        old, new = next(((o, n) for o, n in renames if key.startswith(o)), ("", ""))
        out[new + key[len(old):]] = value
    return out
