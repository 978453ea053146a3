"""`relayrl/PixelCatch-v0`: Catch from pixels (bsuite's Catch, Osband et al. 2020, drawn as frames),
a pixel env that a working pixel pipeline learns in seconds: a check of the frame path (uint8
frames, stacks rebuilt by the replay from one frame per step, the conv net) before hours of
Atari, and the pixel learning test of tests/test_pixel_catch.py.

A ball falls one row per step from a random column of the top row; the paddle on the bottom row
moves left, stays or moves right (actions 0, 1, 2). When the ball reaches the paddle's row the
step's reward is +1 if the paddle is under it, else -1, and a new ball starts at the top;
`balls` balls make an episode. Frames are uint8 [rows * cell, cols * cell] (ball 255, paddle
128), stacked `stack` deep by Gymnasium's FrameStackObservation (its "reset" padding, which the
replay rebuilds stacks from). The defaults give 36x36 frames, which take the Nature CNN as
Atari's do; cell=1 gives 9x9 frames and the small conv net, fast on a CPU.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.wrappers import FrameStackObservation

ROWS = COLS = 9
BALL, PADDLE = 255, 128


class PixelCatch(gym.Env[np.ndarray, np.int64]):
    """One frame per observation; `make_pixel_catch` stacks them."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, cell: int = 4, balls: int = 5, render_mode: str | None = None) -> None:
        if cell < 1 or balls < 1:
            raise ValueError(f"cell={cell} and balls={balls} must be >= 1")
        self.cell, self.balls, self.render_mode = cell, balls, render_mode
        self.observation_space = gym.spaces.Box(0, 255, (ROWS * cell, COLS * cell), np.uint8)
        self.action_space = gym.spaces.Discrete(3)
        self._ball = (0, 0)  # (row, column)
        self._paddle = COLS // 2
        self._caught_or_missed = 0

    def _frame(self) -> np.ndarray:
        c = self.cell
        frame = np.zeros((ROWS * c, COLS * c), np.uint8)
        row, col = self._ball
        frame[row * c:(row + 1) * c, col * c:(col + 1) * c] = BALL
        frame[(ROWS - 1) * c:, self._paddle * c:(self._paddle + 1) * c] = PADDLE
        return frame

    def _new_ball(self) -> None:
        self._ball = (0, int(self.np_random.integers(COLS)))

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self._paddle = COLS // 2
        self._caught_or_missed = 0
        self._new_ball()
        return self._frame(), {}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if not self.action_space.contains(action):
            raise ValueError(f"action {action!r} is not in {self.action_space}")
        self._paddle = min(max(self._paddle + int(action) - 1, 0), COLS - 1)
        row, col = self._ball
        reward = 0.0
        if row + 1 == ROWS - 1:  # the ball reaches the paddle's row
            reward = 1.0 if col == self._paddle else -1.0
            self._caught_or_missed += 1
            self._new_ball()
        else:
            self._ball = (row + 1, col)
        return self._frame(), reward, self._caught_or_missed >= self.balls, False, {}

    def render(self) -> np.ndarray:
        return np.repeat(self._frame()[:, :, None], 3, axis=2)


def make_pixel_catch(cell: int = 4, balls: int = 5, stack: int = 4, render_mode: str | None = None
                     ) -> gym.Env:
    """PixelCatch with its frames stacked `stack` deep (1: single frames)."""
    if stack < 1:
        raise ValueError(f"stack={stack} must be >= 1")
    env: gym.Env = PixelCatch(cell, balls, render_mode)
    return FrameStackObservation(env, stack, padding_type="reset") if stack > 1 else env
