"""Environments: every env is batched (leading batch dim, batch >= 1)."""

from relayrl.envs.gym import GymBatchEnv, make_env, resolve_env_fn

__all__ = ["GymBatchEnv", "make_env", "resolve_env_fn"]
