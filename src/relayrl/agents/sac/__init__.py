"""Soft Actor-Critic with twin critics and automatic entropy tuning."""

from relayrl.agents.sac.agent import SACAgent
from relayrl.agents.sac.config import SACConfig
from relayrl.agents.sac.losses import actor_loss, alpha_loss, critic_loss, critic_targets, tanh_gaussian

__all__ = ["SACAgent", "SACConfig", "actor_loss", "alpha_loss", "critic_loss", "critic_targets", "tanh_gaussian"]
