"""PPO: clipped surrogate, GAE(lambda), on-policy rollouts through a Queue table."""

from relayrl.agents import lazy_exports

__all__ = ["PPOAgent", "PPOConfig", "gae", "policy_loss", "value_loss"]

__getattr__ = lazy_exports(__name__, {"PPOAgent": "agent", "PPOConfig": "config", "gae": "advantages",
                                      "policy_loss": "losses", "value_loss": "losses"})
