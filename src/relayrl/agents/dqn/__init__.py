"""DQN and Double DQN (`double = true`)."""

from relayrl.agents.dqn.agent import DQNAgent
from relayrl.agents.dqn.config import DQNConfig
from relayrl.agents.dqn.losses import dqn_loss, td_targets

__all__ = ["DQNAgent", "DQNConfig", "dqn_loss", "td_targets"]
