"""`relayrl video`: an MP4 (or GIF, MKV, ...) of the saved greedy policy, from Gymnasium `rgb_array` frames."""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
import torch

from relayrl import atomic
from relayrl.console import say
from relayrl.envs.gym import GymBatchEnv
from relayrl.envs.make import gl_hint, making
from relayrl.envs.resolve import no_display, resolve_env_fn
from relayrl.errors import UserError, check_count
from relayrl.export import load_policy
from relayrl.paths import output_path, writing
from relayrl.presets import load_config
from relayrl.seeding import check_seed

if TYPE_CHECKING:
    from relayrl.training.run_dir import RunDir


def record_video(run_dir: str | Path, out: str | Path | None = None, episodes: int = 1,
                 seed: int | None = 0, max_steps: int = 10_000, env: Any = None) -> Path:
    """A video of the run's saved greedy policy playing `episodes` whole episodes (copy reset
    with `seed`; at most `max_steps` steps in all), written as RUN_DIR/video.mp4 or `out` (.mp4,
    .gif, .mkv, .mov, .avi); returns its path.

    `env`: instead of the run's env.id (a run trained on an env factory in a notebook), a
    callable taking `render_mode` and returning an env, or an env made with render_mode="rgb_array"
    (used as it is and left open)."""
    from relayrl.training.run_dir import RunDir

    # refused, not one episode in their place
    episodes, max_steps = check_count("episodes", episodes), check_count("max_steps", max_steps)
    seed = check_seed(seed)  # None: unseeded; else before Gymnasium's reset says it in its words
    rd = RunDir.of(run_dir)  # RUN_DIR/policy/policy.pt and RUN_DIR/config.toml name the run, as for `relayrl eval`
    if not rd.config.is_file():
        rd = RunDir(run_dir)  # a lone policy file or another folder: `require` says which
    rd.require()
    path = output_path(out, rd.root / "video.mp4")
    if path.suffix.lower() not in VIDEO_SUFFIXES:  # said before the episodes are played, not after
        raise UserError(f"--out {str(path)!r}: {path.suffix} is not a video format relayrl writes; valid: "
                        f"{', '.join(VIDEO_SUFFIXES)}")
    with _headless():
        frames, fps = _frames(rd, policy=load_policy(rd.root), env=env, episodes=episodes, seed=seed,
                              max_steps=max_steps)
    import imageio.v2 as imageio

    # macro_block_size=1: imageio does not resize frames to multiples of 16 (with a warning);
    # `even_sized` pads an odd side by one pixel instead. The temp name keeps the suffix imageio
    # picks the format from, and a video already there stays until the new one is complete.
    # (A GIF, written by Pillow, takes each frame's duration in ms instead.)
    gif = path.suffix.lower() == ".gif"
    timing = {"duration": 1000 / fps} if gif else {"fps": fps, "macro_block_size": 1}
    with writing(path), atomic.replacing(path, ".tmp-" + path.name) as tmp:
        imageio.mimwrite(tmp, frames if gif else [even_sized(f) for f in frames], **timing)
        if tmp.stat().st_size == 0:  # ffmpeg failed without imageio raising: no empty file under the name
            raise UserError(f"--out {str(path)!r}: ffmpeg wrote no video from frames of shape "
                            f"{np.shape(frames[0])}; try --out with .gif")
    return path


def even_sized(frame: Any) -> np.ndarray:
    """`frame` with its last row / column repeated where its height / width is odd: ffmpeg's
    H.264 (yuv420p) takes only even sides, and on an odd one it writes an empty file without
    imageio raising (a GIF keeps any size)."""
    array = np.asarray(frame)
    h, w = array.shape[:2]
    if h % 2 == 0 and w % 2 == 0:
        return array
    return np.pad(array, [(0, h % 2), (0, w % 2)] + [(0, 0)] * (array.ndim - 2), mode="edge")  # gray or RGB


PROGRESS_S = 10.0  # a line this often while the frames are rendered
VIDEO_SUFFIXES = (".mp4", ".gif", ".mkv", ".mov", ".avi")  # not .webm: ffmpeg's default H.264 writes a broken one


@contextlib.contextmanager
def _headless() -> Iterator[None]:
    """Off-screen rendering needs no display or sound: without these, pygame-based envs
    (Pendulum) print an SDL "XDG_RUNTIME_DIR is invalid" error on headless machines, and MuJoCo
    tries GLFW, which needs a display, and prints its warnings before failing (EGL renders
    without one). Put back afterwards, so a notebook's own `render_mode="human"` env later gets
    its window. A user's own settings stay."""
    wanted = {"SDL_VIDEODRIVER": "dummy", "SDL_AUDIODRIVER": "dummy", **({"MUJOCO_GL": "egl"} if no_display() else {})}
    added = {k: v for k, v in wanted.items() if k not in os.environ}
    os.environ.update(added)
    try:
        yield
    finally:
        for k in added:
            os.environ.pop(k, None)


def _frames(rd: RunDir, policy: Any, env: Any, episodes: int, seed: int | None, max_steps: int
            ) -> tuple[list[Any], int]:
    """The RGB frames of `episodes` episodes of `policy` on the run's env (or `env`), and its fps."""
    config = load_config(str(rd.config))
    given = env
    frames: list[Any] = []  # RGB arrays
    make_one = (resolve_env_fn(config.env.id, config.env.max_episode_steps, "rgb_array", config.eval_env_kwargs(),
                               config.env.wrappers) if given is None else lambda: _rgb_env(given))
    with making(config.env.id, users_code=bool(config.env.wrappers) or given is not None):
        env = GymBatchEnv([lambda: EndFrames(make_one(), frames)])
    try:
        # another env= than the run's: one line, as `evaluate` says it
        policy.check_fits(env.observation_spec, env.action_spec)
        fps = int(env.envs[0].metadata.get("render_fps", 30))
        obs = env.reset(seed=seed)
        frames.append(first_frame(env, config.env.id))
        finished = 0
        said_at = time.monotonic()
        for _ in range(max_steps):
            with torch.inference_mode():
                out_step = env.step(policy(obs))
            if bool((out_step.terminated | out_step.truncated)[0]):
                finished += 1
                if finished >= episodes:
                    break
            obs = out_step.obs
            frames.append(env.render())
            if time.monotonic() - said_at >= PROGRESS_S:  # software rendering (MuJoCo's EGL) takes minutes
                said_at = time.monotonic()
                say(f"video: {len(frames):,} frames so far, episode {finished + 1} of {episodes}")
    finally:
        if not isinstance(given, gym.Env):  # the caller's own instance stays open
            env.close()
    return frames, fps


class EndFrames(gym.Wrapper):
    """Adds the frame of each episode's last state to `frames`: the batched env resets its copy
    as soon as an episode ends, so a render after its step shows the next episode's start."""

    def __init__(self, env: gym.Env, frames: list[Any]) -> None:
        super().__init__(env)
        self.frames = frames

    def step(self, action: Any) -> tuple[Any, Any, bool, bool, dict[str, Any]]:
        out = self.env.step(action)
        if out[2] or out[3]:
            self.frames.append(self.env.render())
        return out


def _rgb_env(env: Any) -> gym.Env:
    """The env a video is recorded from: `env` itself, or `env(render_mode="rgb_array")`."""
    if isinstance(env, gym.Env):
        made = env
    elif callable(env):
        try:
            made = env(render_mode="rgb_array")
        except TypeError as e:
            if "render_mode" not in str(e):
                raise
            raise UserError("env= for a video must take render_mode (e.g. lambda render_mode=None: "
                            "MyEnv(render_mode=render_mode)), or be an env made with render_mode='rgb_array'") from None
        if not isinstance(made, gym.Env):
            raise UserError(f"env= returned {type(made).__name__}, not a gymnasium.Env")
    else:
        raise UserError(f"env={env!r} is not an env: give a callable taking render_mode, or a Gymnasium env "
                        "made with render_mode='rgb_array'")
    if made.render_mode != "rgb_array":
        raise UserError(f"env= renders with render_mode={made.render_mode!r}; a video needs render_mode='rgb_array'")
    return made


def first_frame(env: Any, env_id: str) -> np.ndarray:
    """The frame after reset, or one line saying why the env gives none."""
    need = "relayrl video needs render() to return an RGB array (render_mode='rgb_array')"
    try:
        frame = env.render()
    except Exception as e:  # the env's own error: what it said, in one line
        said = " ".join(str(e).split())
        raise UserError(f"env {env_id!r} cannot render: render() raised {type(e).__name__}"
                        f"{': ' + said if said else ' (the env has no render())'}; {need}{gl_hint(e)}") from None
    if frame is None:
        raise UserError(f"env {env_id!r} renders no frames: render() returned None; {need}")
    array = np.asarray(frame)
    if array.ndim != 3 or array.shape[-1] not in (3, 4):
        raise UserError(f"env {env_id!r} renders {type(frame).__name__} of shape {array.shape}, not an image; {need}")
    return frame
