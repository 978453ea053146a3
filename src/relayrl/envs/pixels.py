"""Pixel preprocessing: frame skip, grayscale, resize to 84x84, frame stack; uint8 throughout.

Built from Gymnasium's wrappers (AtariPreprocessing, MaxAndSkipObservation,
GrayscaleObservation, ResizeObservation, FrameStackObservation). Observations stay uint8
[k, 84, 84] until the Q-network, which scales by 1/255 itself: the replay then stores one
byte per pixel, and only each step's newest frame (`frame_stack_of` tells the replay that the
stacks are FrameStackObservation's, whose older frames repeat the previous steps' frames).
"""

from __future__ import annotations

from typing import Any, SupportsFloat

import gymnasium as gym
from gymnasium.wrappers import (
    AtariPreprocessing,
    FrameStackObservation,
    GrayscaleObservation,
    MaxAndSkipObservation,
    ResizeObservation,
)

from relayrl.errors import UserError, install

SCREEN = 84  # Mnih et al. 2015 (Nature DQN) and the Mario tutorial
STACK = 4
SKIP = 4


def require_cv2(what: str) -> None:
    """Gymnasium resizes with OpenCV; say which extra brings it instead of a deep ImportError."""
    try:
        import cv2  # noqa: F401
    except ImportError:
        raise UserError(f"{what} needs OpenCV to resize frames: {install('atari')} "
                        "(or opencv-python-headless)") from None


class SkipFrame(gym.Wrapper):
    """Repeat each action `skip` times, summing the rewards; return the last observation.

    The Mario tutorial's SkipFrame, except that a truncation also stops the repeat (the
    tutorial stops on `done` only and would step a truncated env).
    """

    def __init__(self, env: gym.Env, skip: int = SKIP) -> None:
        super().__init__(env)
        if skip < 1:
            raise ValueError(f"skip={skip} is not valid; it must be >= 1")
        self.skip = skip

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        total = 0.0
        for _ in range(self.skip):
            obs, reward, terminated, truncated, info = self.env.step(action)
            total += float(reward)
            if terminated or truncated:
                break
        return obs, total, terminated, truncated, info


def atari_preprocessing(env: gym.Env, frame_skip: int = SKIP, screen_size: int = SCREEN, stack: int = STACK,
                        noop_max: int = 30, terminal_on_life_loss: bool = False) -> gym.Env:
    """The standard DQN stack for an ALE env made with `frameskip=1`: up to `noop_max` no-ops
    at reset, frame skip summing rewards with a max over the last two frames (Atari sprites
    flicker between frames), grayscale, resize (area interpolation), stack of `stack`.

    No life-loss terminations and no reward clipping by default (Machado et al. 2018): the
    returns relayrl reports are the game's scores.
    """
    require_cv2("Atari preprocessing")
    env = AtariPreprocessing(env, noop_max=noop_max, frame_skip=frame_skip, screen_size=screen_size,
                             terminal_on_life_loss=terminal_on_life_loss, grayscale_obs=True, scale_obs=False)
    return FrameStackObservation(env, stack, padding_type="reset")


def mario_preprocessing(env: gym.Env, skip: int = SKIP, screen_size: int = SCREEN, stack: int = STACK,
                        max_pool: bool = False) -> gym.Env:
    """The Mario tutorial's stack for any RGB env ([H, W, 3] uint8): SkipFrame(skip, summed
    rewards), grayscale, resize to screen_size x screen_size, FrameStack(stack), uint8.

    The tutorial's ResizeObservation also scaled to [0, 1] floats; here the network does that,
    so frames stay one byte per pixel. `max_pool=True` takes Gymnasium's MaxAndSkipObservation
    (rewards summed, max over the last two frames) instead of SkipFrame.
    """
    require_cv2("Pixel preprocessing")
    shape = env.observation_space.shape
    if shape is None or len(shape) != 3 or shape[-1] != 3:
        raise UserError(f"pixel preprocessing needs RGB observations [H, W, 3], got {shape}")
    fps = env.metadata.get("render_fps")
    env = MaxAndSkipObservation(env, skip) if max_pool else SkipFrame(env, skip)
    env = GrayscaleObservation(env, keep_dim=False)  # [H, W] uint8
    env = ResizeObservation(env, (screen_size, screen_size))  # [84, 84] uint8
    env = FrameStackObservation(env, stack, padding_type="reset")  # [stack, 84, 84] uint8
    if fps:  # one step renders every skip-th frame: videos play in real time
        env.metadata = {**env.metadata, "render_fps": max(1, round(fps / skip))}
    return env


def frame_stack_of(env: gym.Env) -> int:
    """k when the env's observations are FrameStackObservation's stacks of k frames with
    "reset" padding (what the replay rebuilds from one stored frame per step), else 1.

    Only wrappers that leave observations alone may sit outside the stack: a transform of
    whole stacks could break "the older frames are the previous steps' frames".
    """
    while isinstance(env, gym.Wrapper):
        if isinstance(env, FrameStackObservation):
            return env.stack_size if env.padding_type == "reset" and env.stack_size > 1 else 1
        if isinstance(env, gym.ObservationWrapper) or env.observation_space is not env.env.observation_space:
            return 1
        env = env.env
    return 1
