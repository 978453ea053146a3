"""Stateless envs for the rest of relayrl: as a batched env for the train loop
(`StatelessBatchEnv`, `make_batch_env`), and as a single Gymnasium env (`StatelessGymEnv`) for
tools that go through Gymnasium (video, `gymnasium.make`).

`StatelessBatchEnv` holds the state the stateless env does not: the current state of
`num_envs` rows and its generators. Rows whose episode ended are reset inside `step`, and
`StepOutput` keeps the true final observation (`next_obs`) apart from the observation the
next action is taken from (`obs`), as `envs/gym.py` does. Every tensor stays on the adapter's
device, so env, policy and replay can share one GPU. Stepping runs under `no_grad`: this is
for RL loops; differentiate through `rollout` instead.

On a GPU a batched step is launch-bound (dozens of kernels on a few thousand numbers), so it
replays from a CUDA graph (`nn.graphed.GraphedStep`; `RELAYRL_CUDA_GRAPHS=0` launches it op by
op) where the env is `graph_safe`: the env's step and the fresh states of rows whose episode
ended, drawn every step from a generator on the GPU (seeded from the CPU one at `reset`) and
kept where `done`, so nothing branches on a value. The first states come from the CPU
generator on every device.
"""

from __future__ import annotations

import pickle
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from relayrl.core import BatchedEnv
from relayrl.envs.stateless.base import DeviceLike, StatelessEnv, tree_leaves, tree_map, tree_where
from relayrl.envs.stateless.pendulum import make_pendulum
from relayrl.errors import UserError
from relayrl.nn.graphed import GraphedStep, cuda_graphs_enabled
from relayrl.specs import ArraySpec
from relayrl.types import StepOutput

STEP_FIELDS = ("next_obs", "reward", "terminated", "truncated", "obs")  # a graphed step's outputs besides the state


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
        # Off the CPU, fresh states are drawn on the device every step (see the module doc).
        self._device_gen = torch.Generator(device=self.device) if self.device.type != "cpu" else None
        self._graphed = None
        if self._device_gen is not None and env.graph_safe and cuda_graphs_enabled(self.device):
            self._graphed = GraphedStep(self._graph_step, generators=[self._device_gen])
        self._state: Any = None

    def reset(self, seed: int | None = None) -> torch.Tensor:
        """Reset every row; observations [B, *obs_shape]."""
        if seed is not None:
            self._gen.manual_seed(seed)
        self._state, obs = self.env.reset((self.num_envs,), self._gen, self.device)
        if self._device_gen is not None:
            self._device_gen.manual_seed(int(torch.randint(2**62, (), generator=self._gen)))
        return obs[self.obs_key]

    @torch.no_grad()
    def step(self, action: torch.Tensor) -> StepOutput:
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        action = action.to(self.device)
        if self._graphed is None:
            self._state, *fields = self._advance(self._state, action)
        else:
            out = self._graphed(*self._leaves(), action)
            self._state = self._rebuild([out[f"state/{i}"] for i in range(len(out) - len(STEP_FIELDS))])
            # The graph's outputs are overwritten by its next replay: observers may keep a step's
            # tensors until they flush (episode statistics do), so they get copies.
            fields = [out[k].clone() for k in STEP_FIELDS]
        next_obs, reward, terminated, truncated, obs = fields
        if self.time_limit_terminates:
            terminated, truncated = terminated | truncated, torch.zeros_like(truncated)
        return StepOutput(next_obs, reward, terminated, truncated, obs)

    def _advance(self, state: Any, action: torch.Tensor) -> tuple[Any, ...]:
        """One batched step: the new state, the true next observations, rewards, terminated and
        truncated flags, and the observations the next action sees (fresh where `done`)."""
        out = self.env.step(state, action)
        next_obs = out.obs[self.obs_key]  # [B, *obs_shape]
        done = out.terminated | out.truncated  # [B]
        state, obs = out.state, next_obs
        # Rows are reset where an episode ended: on the CPU only when one did (reading `done`
        # is free there); on a device every step, from its own generator (no branch on a value).
        gen = self._gen if self._device_gen is None else self._device_gen
        if self._device_gen is not None or bool(done.any()):
            fresh_state, fresh_obs = self.env.reset((self.num_envs,), gen, self.device)
            state = tree_where(done, fresh_state, out.state)
            obs = torch.where(done.view(-1, *([1] * (next_obs.dim() - 1))), fresh_obs[self.obs_key], next_obs)
        return state, next_obs, out.reward.to(torch.float32), out.terminated, out.truncated, obs

    def _graph_step(self, *tensors: torch.Tensor) -> dict[str, torch.Tensor]:
        """`_advance` on the state's leaves and the action, as a CUDA graph captures it: the
        new state's leaves (`state/<i>`) and the STEP_FIELDS."""
        *leaves, action = tensors
        state, *fields = self._advance(self._rebuild(list(leaves)), action)
        return {**{f"state/{i}": leaf for i, (_, leaf) in enumerate(tree_leaves(state))},
                **dict(zip(STEP_FIELDS, fields, strict=True))}

    def _leaves(self) -> list[torch.Tensor]:
        return [leaf for _, leaf in tree_leaves(self._state)]

    def _rebuild(self, leaves: list[torch.Tensor]) -> Any:
        """The state's structure with `leaves` in its leaves' order."""
        it = iter(leaves)
        return tree_map(lambda _: next(it), self._state)

    def get_state(self) -> list[bytes]:
        """One pickled row per env copy (the generators' states ride with row 0), for
        checkpoints that resume mid-episode (see training/actor.py)."""
        rng = (self._gen.get_state(), None if self._device_gen is None else self._device_gen.get_state())
        return [pickle.dumps((tree_map(lambda x, i=i: x[i].detach().cpu().clone(), self._state),
                              rng if i == 0 else None)) for i in range(self.num_envs)]

    def set_state(self, states: list[bytes]) -> None:
        rows = [pickle.loads(s) for s in states]
        self._state = tree_map(lambda *xs: torch.stack(xs).to(self.device), *(r[0] for r in rows))
        rng = rows[0][1]
        cpu, device = rng if isinstance(rng, tuple) else (rng, None)  # checkpoints before the device's generator
        self._gen.set_state(cpu)
        if self._device_gen is not None:
            if device is not None:
                self._device_gen.set_state(device)
            else:  # saved on the CPU: seeded as a reset seeds it
                self._device_gen.manual_seed(int(torch.randint(2**62, (), generator=self._gen)))

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
        # STATELESS_ENVS' observations and actions are bounded, as a Box needs
        assert spec.low is not None and spec.high is not None and act.low is not None and act.high is not None
        self.observation_space = gym.spaces.Box(spec.low.astype(np.float32), spec.high.astype(np.float32),
                                                dtype=np.float32)
        self.action_space = gym.spaces.Box(act.low.astype(np.float32), act.high.astype(np.float32), dtype=np.float32)
        self.render_mode = render_mode
        self._gen, self._state = torch.Generator(), None
        self._last_u: float | None = None  # the last torque, for the renderer
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
