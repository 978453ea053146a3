"""The env step's observation write for frames: env steps/s of 8 copies of a Dict env (uint8
frame [3, 36, 36] + float32 vector [4], packed into one row per copy) and of 8 PixelCatch copies
(uint8 frames), through `GymBatchEnv.step`, random-free constant actions.

    PYTHONPATH=A_CHECKOUT/src python bench/obs_write.py    # then B_CHECKOUT, alternating

Prints "<dict env steps/s> <pixel catch env steps/s>"; a same-run A/B alternates checkouts.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from relayrl.envs import make_env
from relayrl.envs.gym import GymBatchEnv


class FrameAndVector(gym.Env):
    """A Dict observation of a uint8 frame and a float32 vector; episodes of 100 steps."""

    observation_space = gym.spaces.Dict({"frame": gym.spaces.Box(0, 255, (3, 36, 36), np.uint8),
                                         "vec": gym.spaces.Box(-1, 1, (4,), np.float32)})
    action_space = gym.spaces.Discrete(2)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[Any, dict]:
        super().reset(seed=seed)
        self.t = 0
        return self._obs(), {}

    def _obs(self) -> dict[str, np.ndarray]:
        return {"frame": np.zeros((3, 36, 36), np.uint8), "vec": np.zeros(4, np.float32)}

    def step(self, action: int) -> tuple[Any, float, bool, bool, dict]:
        self.t += 1
        return self._obs(), 0.0, False, self.t >= 100, {}


def rate(env: Any, steps: int) -> float:
    env.reset(seed=0)
    act = torch.zeros(env.num_envs, dtype=torch.int64)
    for _ in range(200):
        env.step(act)
    t = time.perf_counter()
    for _ in range(steps):
        env.step(act)
    return env.num_envs * steps / (time.perf_counter() - t)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=3000, help="batched steps timed per env (default 3000)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"{rate(GymBatchEnv([FrameAndVector] * 8), args.steps):.0f} "
          f"{rate(make_env('relayrl/PixelCatch-v0', 8), args.steps):.0f}")


if __name__ == "__main__":
    main()
