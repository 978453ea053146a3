"""The Q-network for discrete actions, built from specs."""

from __future__ import annotations

from relayrl.agents.dqn.config import DQNConfig
from relayrl.errors import UserError
from relayrl.networks import MLP, tf_agents_init_
from relayrl.specs import DiscreteSpec, Spec, flat_dim


def q_network(obs_spec: Spec, action_spec: Spec, cfg: DQNConfig) -> MLP:
    if not isinstance(action_spec, DiscreteSpec):
        raise UserError("DQN needs a discrete action space (gymnasium.spaces.Discrete); "
                        "use SAC for continuous actions")
    net = MLP(flat_dim(obs_spec), list(cfg.hidden), action_spec.n, cfg.activation)
    if cfg.init == "tf-agents":
        tf_agents_init_(net)
    return net
