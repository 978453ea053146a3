"""Environments: every env is batched (leading batch dim, batch >= 1)."""

import gymnasium

from relayrl.envs.atari import register_shipped_games
from relayrl.envs.gym import GymBatchEnv
from relayrl.envs.make import make_env
from relayrl.envs.mario import ENV_ID as MARIO_ID
from relayrl.envs.mario import PIXELS_ID as MARIO_PIXELS_ID
from relayrl.envs.resolve import resolve_env_fn

# By entry-point string, so importing relayrl.envs never imports an extra (pybullet, nes-py).
# StatelessPendulum: a stateless torch env as one Gymnasium env (videos, gym.make) that truncates
# itself at 200 steps; the train loop batches it directly (envs/stateless/adapter.py) instead.
# PixelCatch: a pixel env learnt in seconds (envs/catch.py).
# Super Mario Bros: the raw NES screen (the level clock ends episodes within ~8,000 frames), and
# the tutorial's preprocessed stack on top (skip 4, summed rewards, grayscale, 84x84, stack 4;
# its frame limit sits under the skip).
for _id, _entry_point, _max_steps in (
    ("relayrl/MinitaurBullet-v0", "relayrl.envs.minitaur:MinitaurEnv", 1000),
    ("relayrl/PixelCatch-v0", "relayrl.envs.catch:make_pixel_catch", None),
    ("relayrl/StatelessPendulum-v0", "relayrl.envs.stateless.adapter:StatelessGymEnv", None),
    (MARIO_ID, "relayrl.envs.mario:MarioEnv", 10_000),
    (MARIO_PIXELS_ID, "relayrl.envs.mario:make_preprocessed", None),
):
    if _id not in gymnasium.registry:
        gymnasium.register(_id, entry_point=_entry_point, max_episode_steps=_max_steps)
register_shipped_games()  # relayrl/Atari-<Game>-v0, where ale-py is installed

__all__ = ["GymBatchEnv", "make_env", "resolve_env_fn"]
