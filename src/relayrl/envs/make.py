"""`make_env`: a batched env from an id, with the copies stepped here, in worker processes, or
as one stateless torch batch. It sits above gym.py and vector.py, which know nothing of it."""

from __future__ import annotations

import gymnasium as gym
import torch

from relayrl.envs.gym import BatchEnvBase, GymBatchEnv, resolve_env_fn
from relayrl.envs.stateless.adapter import STATELESS_ENVS, make_batch_env
from relayrl.envs.vector import AsyncGymBatchEnv
from relayrl.errors import UserError


def make_env(env_id: str, num_envs: int = 1, max_episode_steps: int = 0, render_mode: str | None = None,
             time_limit_terminates: bool = False, vectorization: str = "sync",
             device: str | torch.device = "cpu", info_keys: tuple[str, ...] | list[str] = (),
             num_workers: int = 0) -> GymBatchEnv:
    """A batched env of `num_envs` copies of `env_id`: stepped in this process ("sync") or
    shared out over `num_workers` worker processes ("async", 0: one per core; see envs/vector.py).
    A stateless torch env id (`relayrl/StatelessPendulum-v0`) gives all copies as one batch of
    tensors on `device`.
    `info_keys`: info values to report at each episode's end (`StepOutput.episode_info`)."""
    if env_id in STATELESS_ENVS and render_mode is None:
        if info_keys:
            raise UserError(f"env.info_keys is not supported by stateless envs ({env_id!r} has no info dict)")
        return make_batch_env(env_id, num_envs, device, max_episode_steps=max_episode_steps,  # type: ignore[return-value]
                              time_limit_terminates=time_limit_terminates)
    fn = resolve_env_fn(env_id, max_episode_steps, render_mode)
    try:
        env: BatchEnvBase
        if vectorization == "async" and num_envs > 1:
            env = AsyncGymBatchEnv([fn] * num_envs, time_limit_terminates, num_workers)
        else:
            env = GymBatchEnv([fn] * num_envs, time_limit_terminates)
    except gym.error.Error as e:
        raise UserError(f"env.id={env_id!r} could not be made: {e}") from None
    env.info_keys = tuple(info_keys)
    return env  # type: ignore[return-value]
