"""`relayrl video`: an MP4 of the saved greedy policy, from Gymnasium `rgb_array` frames."""

from __future__ import annotations

import os
from pathlib import Path

import torch

from relayrl.envs import make_env
from relayrl.errors import UserError
from relayrl.export import load_policy
from relayrl.paths import output_path
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
        frames = []
        obs = env.reset(seed=seed)
        finished = 0
        for _ in range(max_steps):
            frames.append(env.render())
            with torch.inference_mode():
                out_step = env.step(policy(obs))
            if bool((out_step.terminated | out_step.truncated)[0]):
                finished += 1
                if finished >= episodes:
                    break
            obs = out_step.obs
    finally:
        env.close()
    if not frames or frames[0] is None:
        raise UserError(f"env {config.env.id!r} does not render rgb_array frames")
    import imageio.v2 as imageio

    # macro_block_size=1 keeps odd frame sizes as they are instead of resizing with a warning.
    imageio.mimwrite(path, frames, fps=fps, macro_block_size=1)
    return path
