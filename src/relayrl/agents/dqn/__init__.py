"""DQN and Double DQN (`double = true`)."""

from relayrl.agents import lazy_exports

__all__ = ["DQNAgent", "DQNConfig", "dqn_loss", "td_targets"]

__getattr__ = lazy_exports(__name__, {"DQNAgent": "agent", "DQNConfig": "config", "dqn_loss": "losses",
                                      "td_targets": "losses"})
