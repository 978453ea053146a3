"""Soft Actor-Critic with twin critics and automatic entropy tuning."""

from relayrl.agents import lazy_exports

__all__ = ["SACAgent", "SACConfig", "actor_loss", "alpha_loss", "critic_loss", "critic_targets", "tanh_gaussian"]

__getattr__ = lazy_exports(__name__, {"SACAgent": "agent", "SACConfig": "config", **dict.fromkeys(
    ("actor_loss", "alpha_loss", "critic_loss", "critic_targets", "tanh_gaussian"), "losses")})
