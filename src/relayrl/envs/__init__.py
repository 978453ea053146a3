"""Environments: every env is batched (leading batch dim, batch >= 1)."""

import gymnasium

from relayrl.envs.gym import GymBatchEnv, make_env, resolve_env_fn

# By entry-point string, so importing relayrl.envs never imports pybullet (an extra).
if "relayrl/MinitaurBullet-v0" not in gymnasium.registry:
    gymnasium.register(
        "relayrl/MinitaurBullet-v0", entry_point="relayrl.envs.minitaur:MinitaurEnv", max_episode_steps=1000
    )

__all__ = ["GymBatchEnv", "make_env", "resolve_env_fn"]
