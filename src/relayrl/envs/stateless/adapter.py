"""Stateless envs for the rest of relayrl: as a batched env for the train loop
(`StatelessBatchEnv`, `make_batch_env`), and as a single Gymnasium env (`StatelessGymEnv`) for
tools that go through Gymnasium (video, `gymnasium.make`).

`StatelessBatchEnv` holds the state the stateless env does not: the current state of
`num_envs` rows and one generator. Rows whose episode ended are reset inside `step`, and
`StepOutput` keeps the true final observation (`next_obs`) apart from the observation the
next action is taken from (`obs`), as `envs/gym.py` does. Every tensor stays on the adapter's
device, so env, policy and replay can share one GPU. Stepping runs under `no_grad`: this is
for RL loops; differentiate through `rollout` instead.
"""

from __future__ import annotations

import pickle
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from relayrl.core import BatchedEnv
from relayrl.envs.stateless.base import DeviceLike, StatelessEnv, tree_map, tree_where
from relayrl.envs.stateless.pendulum import make_pendulum
from relayrl.errors import UserError
from relayrl.specs import ArraySpec
from relayrl.types import StepOutput


class StatelessBatchEnv(BatchedEnv):
    """`num_envs` rows of `env` as one BatchedEnv; the observation is `obs[obs_key]`."""

    def __init__(self, env: StatelessEnv, num_envs: int, device: DeviceLike = None, obs_key: str = "observation",
                 seed: int | None = None, time_limit_terminates: bool = False) -> None:
        if num_envs < 1:
            raise UserError("env.num_envs must be >= 1")
        if obs_key not in env.observation_spec:
            raise UserError(f"the env observes {sorted(env.observation_spec)}, not {obs_key!r} "
                            "(wrap it in a TransformedEnv that builds one tensor, e.g. make_pendulum())")
        self.env, self.num_envs, self.obs_key = env, num_envs, obs_key
        self.device = torch.device(device) if device is not None else env.device
        self.observation_spec: ArraySpec = env.observation_spec[obs_key]
        self.action_spec: ArraySpec = env.action_spec
        # Old gym reported a time-limit cut as a termination; some presets reproduce that.
        self.time_limit_terminates = time_limit_terminates
        # A CPU generator: the same seed gives the same first episodes on every device.
        self._gen = torch.Generator()
        if seed is None:
            self._gen.seed()
        else:
            self._gen.manual_seed(seed)
        self._state: Any = None

    def reset(self, seed: int | None = None) -> torch.Tensor:
        """Reset every row; observations [B, *obs_shape]."""
        if seed is not None:
            self._gen.manual_seed(seed)
        self._state, obs = self.env.reset((self.num_envs,), self._gen, self.device)
        return obs[self.obs_key]

    @torch.no_grad()
    def step(self, action: torch.Tensor) -> StepOutput:
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        out = self.env.step(self._state, action.to(self.device))
        next_obs = out.obs[self.obs_key]  # [B, *obs_shape]
        terminated, truncated = out.terminated, out.truncated
        done = terminated | truncated  # [B]
        state, obs = out.state, next_obs
        # Rows are reset where an episode ended. Reading `done` is free on the CPU, which draws
        # fresh states only then; on a GPU the read would make the host wait at every step, so
        # fresh states are drawn every step there (another generator stream than the CPU's).
        if self.device.type != "cpu" or bool(done.any()):
            fresh_state, fresh_obs = self.env.reset((self.num_envs,), self._gen, self.device)
            state = tree_where(done, fresh_state, out.state)
            obs = torch.where(done.view(-1, *([1] * (next_obs.dim() - 1))), fresh_obs[self.obs_key], next_obs)
        self._state = state
        if self.time_limit_terminates:
            terminated, truncated = done, torch.zeros_like(done)
        return StepOutput(next_obs, out.reward.to(torch.float32), terminated, truncated, obs)

    def get_state(self) -> list[bytes]:
        """One pickled row per env copy (the generator's state rides with row 0), for
        checkpoints that resume mid-episode (see training/actor.py)."""
        rng = self._gen.get_state()
        return [pickle.dumps((tree_map(lambda x, i=i: x[i].detach().cpu().clone(), self._state),
                              rng if i == 0 else None)) for i in range(self.num_envs)]

    def set_state(self, states: list[bytes]) -> None:
        rows = [pickle.loads(s) for s in states]
        self._state = tree_map(lambda *xs: torch.stack(xs).to(self.device), *(r[0] for r in rows))
        self._gen.set_state(rows[0][1])

    def close(self) -> None:
        pass


# Stateless envs by id: a factory taking (max_episode_steps, device); 0 steps = the env's default.
STATELESS_ENVS: dict[str, Callable[[int, DeviceLike], StatelessEnv]] = {
    "relayrl/StatelessPendulum-v0": lambda steps, device: make_pendulum(steps or 200, device=device),
}


def make_batch_env(env_id: str, num_envs: int, device: DeviceLike = "cpu", seed: int | None = None,
                   max_episode_steps: int = 0, time_limit_terminates: bool = False) -> StatelessBatchEnv:
    """The batched env for a stateless env id (a key of STATELESS_ENVS)."""
    if env_id not in STATELESS_ENVS:
        raise UserError(f"env.id={env_id!r} is not a stateless env; valid: {sorted(STATELESS_ENVS)}")
    env = STATELESS_ENVS[env_id](max_episode_steps, device)
    return StatelessBatchEnv(env, num_envs, device, seed=seed, time_limit_terminates=time_limit_terminates)


class StatelessGymEnv(gym.Env):
    """One copy (batch shape `()`) of a stateless env as a Gymnasium env, on the CPU, with
    NumPy observations. Rendering borrows Gymnasium's Pendulum-v1 renderer (pendulum only)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(self, env_id: str = "relayrl/StatelessPendulum-v0", render_mode: str | None = None,
                 max_episode_steps: int = 0) -> None:
        self.env = STATELESS_ENVS[env_id](max_episode_steps, "cpu")
        spec = self.env.observation_spec["observation"]
        act = self.env.action_spec
        self.observation_space = gym.spaces.Box(spec.low.astype(np.float32), spec.high.astype(np.float32),
                                                dtype=np.float32)
        self.action_space = gym.spaces.Box(act.low.astype(np.float32), act.high.astype(np.float32), dtype=np.float32)
        self.render_mode = render_mode
        self._gen, self._state, self._last_u = torch.Generator(), None, None
        self._renderer = gym.make("Pendulum-v1", render_mode="rgb_array").unwrapped if render_mode else None

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        if seed is not None:
            self._gen.manual_seed(seed)
        self._state, obs = self.env.reset((), self._gen)
        self._last_u = None
        return obs["observation"].numpy(), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        action_t = torch.as_tensor(np.asarray(action, dtype=np.float32)).reshape(self.env.action_spec.shape)
        out = self.env.step(self._state, action_t)
        self._state, self._last_u = out.state, float(action_t.clamp(-2, 2)[0])
        return out.obs["observation"].numpy(), float(out.reward), bool(out.terminated), bool(out.truncated), {}

    def render(self) -> np.ndarray | None:
        if self._renderer is None or self._state is None:
            return None
        self._renderer.state = np.array([float(self._state.th), float(self._state.thdot)])
        self._renderer.last_u = self._last_u
        return self._renderer.render()
