"""Environments: every env is batched (leading batch dim, batch >= 1)."""

import gymnasium

from relayrl.envs.gym import GymBatchEnv, resolve_env_fn
from relayrl.envs.make import make_env

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

# Super Mario Bros (the [mario] extra), by entry-point string so that importing relayrl.envs
# never imports nes-py: the raw NES screen, and the tutorial's preprocessed stack on top.
if "relayrl/SuperMarioBros-1-1-v0" not in gymnasium.registry:
    gymnasium.register("relayrl/SuperMarioBros-1-1-v0", entry_point="relayrl.envs.mario:MarioEnv",
                       max_episode_steps=10_000)  # raw frames; the level clock ends episodes within ~8,000
if "relayrl/SuperMarioBros-1-1-pixels-v0" not in gymnasium.registry:
    # skip 4 (summed rewards), grayscale, 84x84, stack 4; the frame limit sits under the skip
    gymnasium.register("relayrl/SuperMarioBros-1-1-pixels-v0", entry_point="relayrl.envs.mario:make_preprocessed")

__all__ = ["GymBatchEnv", "make_env", "resolve_env_fn"]
