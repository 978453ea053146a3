"""Agents: one folder per algorithm with config, pure losses, networks and the agent."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from relayrl.specs import Spec


def make_agent(algo: str, agent_cfg: Any, obs_spec: Spec, action_spec: Spec, device: torch.device,
               rng: np.random.Generator, total_steps: int) -> Any:
    """Build the agent named by `algo` (the config layer has already checked the name)."""
    if algo == "dqn":
        from relayrl.agents.dqn import DQNAgent

        return DQNAgent(obs_spec, action_spec, agent_cfg, device, rng, total_steps)
    if algo == "sac":
        from relayrl.agents.sac import SACAgent

        return SACAgent(obs_spec, action_spec, agent_cfg, device, rng, total_steps)
    raise ValueError(f"unknown algo {algo!r}")
