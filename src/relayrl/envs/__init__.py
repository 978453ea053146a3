"""Environments: every env is batched (leading batch dim, batch >= 1)."""

import gymnasium

from relayrl.envs.gym import GymBatchEnv, make_env, resolve_env_fn

# By entry-point string, so importing relayrl.envs never imports pybullet (an extra).
if "relayrl/MinitaurBullet-v0" not in gymnasium.registry:
    gymnasium.register(
        "relayrl/MinitaurBullet-v0", entry_point="relayrl.envs.minitaur:MinitaurEnv", max_episode_steps=1000
    )

# A stateless torch env as one Gymnasium env (videos, gym.make); the train loop batches it
# directly (envs/stateless/adapter.py) instead.
if "relayrl/StatelessPendulum-v0" not in gymnasium.registry:
    gymnasium.register("relayrl/StatelessPendulum-v0",  # truncates itself at 200 steps
                       entry_point="relayrl.envs.stateless.adapter:StatelessGymEnv")

__all__ = ["GymBatchEnv", "make_env", "resolve_env_fn"]
