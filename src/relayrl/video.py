"""`relayrl video`: an MP4 of the saved greedy policy, from Gymnasium `rgb_array` frames."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from relayrl import atomic
from relayrl.envs import make_env
from relayrl.errors import UserError
from relayrl.export import load_policy
from relayrl.paths import output_path, writing
from relayrl.presets import load_config


def record_video(run_dir: str | Path, out: str | Path | None = None, episodes: int = 1,
                 seed: int = 0, max_steps: int = 10_000) -> Path:
    from relayrl.training.run_dir import RunDir

    rd = RunDir(run_dir)
    rd.require()
    path = output_path(out, rd.root / "video.mp4")
    # Off-screen rendering needs no display or sound: without these, pygame-based envs
    # (Pendulum) print an SDL "XDG_RUNTIME_DIR is invalid" error on headless machines.
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    os.environ.setdefault("SDL_AUDIODRIVER", "dummy")
    config = load_config(str(rd.config))
    policy = load_policy(rd.root)
    env = make_env(config.env.id, 1, config.env.max_episode_steps, render_mode="rgb_array",
                   kwargs=config.env.kwargs, wrappers=config.env.wrappers)
    try:
        fps = int(env.envs[0].metadata.get("render_fps", 30))
        obs = env.reset(seed=seed)
        frames = [first_frame(env, config.env.id)]
        finished = 0
        for _ in range(max_steps):
            with torch.inference_mode():
                out_step = env.step(policy(obs))
            if bool((out_step.terminated | out_step.truncated)[0]):
                finished += 1
                if finished >= episodes:
                    break
            obs = out_step.obs
            frames.append(env.render())
    finally:
        env.close()
    import imageio.v2 as imageio

    # macro_block_size=1 keeps odd frame sizes as they are instead of resizing with a warning;
    # the temp name keeps the .mp4 suffix imageio picks the format from, and a video already
    # there stays until the new one is complete.
    with writing(path), atomic.replacing(path, ".tmp-" + path.name) as tmp:
        imageio.mimwrite(tmp, frames, fps=fps, macro_block_size=1)
    return path


def first_frame(env: Any, env_id: str) -> np.ndarray:
    """The frame after reset, or one line saying why the env gives none."""
    need = "relayrl video needs render() to return an RGB array (render_mode='rgb_array')"
    try:
        frame = env.render()
    except Exception as e:  # the env's own error: what it said, in one line
        raise UserError(f"env {env_id!r} cannot render: render() raised {type(e).__name__}: "
                        f"{' '.join(str(e).split())}; {need}") from None
    if frame is None:
        raise UserError(f"env {env_id!r} renders no frames: render() returned None; {need}")
    array = np.asarray(frame)
    if array.ndim != 3 or array.shape[-1] not in (3, 4):
        raise UserError(f"env {env_id!r} renders {type(frame).__name__} of shape {array.shape}, not an image; {need}")
    return frame
