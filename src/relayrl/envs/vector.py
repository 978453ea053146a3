"""Gymnasium envs stepped in worker processes, as one batched env (`env.vectorization = "async"`).

Built on `gymnasium.vector.AsyncVectorEnv` with same-step autoreset: a copy whose episode
ends is reset inside the same `step`, its true final observation comes back in
`info["final_obs"]`, and we put that in `next_obs` and the reset observation in `obs`, so
transitions look exactly as from the in-process `GymBatchEnv` (same seeds, same numbers).
Worth it when one env step costs more than the pipe round trip (~0.1 ms): physics
simulators such as Minitaur, not CartPole.
"""

from __future__ import annotations

import pickle

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode

from relayrl.envs.gym import BatchEnvBase, EnvFn, env_snapshot, episode_info
from relayrl.envs.pixels import frame_stack_of
from relayrl.errors import UserError
from relayrl.types import StepOutput


class _Snapshot(gym.Wrapper):
    """Hands a worker's env state out (pickled) and takes one in, through the vector env's
    `call` / `set_attr` (which can only reach the env's own attributes)."""

    relayrl_state_in: bytes = b""

    def relayrl_get_state(self) -> bytes | None:
        return env_snapshot(self.env)

    def relayrl_frame_stack(self) -> int:
        return frame_stack_of(self.env)

    def relayrl_set_state(self) -> None:
        self.env.close()
        self.env = pickle.loads(self.relayrl_state_in)
        self.relayrl_state_in = b""


class _Wrapped:
    """A picklable env factory (the workers get it through cloudpickle) adding `_Snapshot`."""

    def __init__(self, fn: EnvFn) -> None:
        self.fn = fn

    def __call__(self) -> gym.Env:
        return _Snapshot(self.fn())


class AsyncGymBatchEnv(BatchEnvBase):
    def __init__(self, env_fns: list[EnvFn], time_limit_terminates: bool = False) -> None:
        if not env_fns:
            raise UserError("env.num_envs must be >= 1")
        self.vec = gym.vector.AsyncVectorEnv([_Wrapped(fn) for fn in env_fns], autoreset_mode=AutoresetMode.SAME_STEP)
        self._init_specs(len(env_fns), self.vec.single_observation_space, self.vec.single_action_space,
                         time_limit_terminates, int(self.vec.call("relayrl_frame_stack")[0]))

    def get_state(self) -> list[bytes] | None:
        """As `GymBatchEnv.get_state`, pickled in each worker."""
        states = list(self.vec.call("relayrl_get_state"))
        return None if any(s is None for s in states) else states

    def set_state(self, states: list[bytes]) -> None:
        if len(states) != self.num_envs:
            raise ValueError(f"env state for {len(states)} copies, but this env has {self.num_envs}")
        self.vec.set_attr("relayrl_state_in", list(states))
        self.vec.call("relayrl_set_state")

    def reset(self, seed: int | None = None) -> torch.Tensor:
        obs, _ = self.vec.reset(seed=None if seed is None else [seed + i for i in range(self.num_envs)])
        return torch.from_numpy(np.asarray(obs, dtype=self._obs_dtype))

    def step(self, action: torch.Tensor) -> StepOutput:
        actions = action.numpy().astype(np.int64) if self._discrete else action.numpy()
        obs, reward, terminated, truncated, info = self.vec.step(actions)
        obs = np.asarray(obs, dtype=self._obs_dtype)
        next_obs = obs
        done = terminated | truncated
        if done.any():
            next_obs = obs.copy()
            for i in np.flatnonzero(done):
                next_obs[i] = info["final_obs"][i]
        ended_info = None
        if self.info_keys and done.any():
            final = info["final_info"]  # the ended episodes' last infos (the top level has the resets')
            ended_info = episode_info(self.info_keys, self.num_envs, np.flatnonzero(done).tolist(),
                                      lambda i: {k: v[i] for k, v in final.items()
                                                 if not k.startswith("_") and final[f"_{k}"][i]})
        if self.time_limit_terminates:
            terminated, truncated = done, np.zeros_like(truncated)
        return StepOutput(torch.from_numpy(next_obs), torch.from_numpy(reward.astype(np.float32)),
                          torch.from_numpy(terminated.astype(np.bool_)), torch.from_numpy(truncated.astype(np.bool_)),
                          torch.from_numpy(obs), ended_info)

    def render(self) -> np.ndarray | None:
        raise UserError("rendering needs env.vectorization = 'sync' (the video command uses one in-process env)")

    def close(self) -> None:
        self.vec.close()
