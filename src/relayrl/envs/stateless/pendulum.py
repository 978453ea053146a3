"""Gymnasium's Pendulum-v1 as a stateless torch env (the TorchRL Pendulum tutorial's env).

Dynamics, reward, bounds and the reset distribution are Gymnasium's
(gymnasium/envs/classic_control/pendulum.py), written for tensors of any batch shape. Episodes
are truncated after `max_episode_steps` (200, Gymnasium's TimeLimit), counted by the `step`
field of the state; they never terminate. Raw observations are `th` and `thdot` (shape `()`
each, as in the tutorial); `make_pendulum` adds the transforms that give Gymnasium's
observation `[cos th, sin th, thdot]`.

Precision: Gymnasium integrates in float64. With `dtype=torch.float64` a rollout matches it to
~1e-12 over 200 steps; in float32 (the default, for speed) each single step matches to ~1e-6,
but the pendulum is chaotic near the top, so float32 and float64 trajectories drift apart
over long free runs (up to ~1e-2 after 200 steps from some states).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple, cast

import torch

from relayrl.envs.stateless.base import (
    BatchShape,
    DeviceLike,
    Obs,
    StatelessEnv,
    StepResult,
    as_batch_shape,
    bounded,
    uniform,
)
from relayrl.envs.stateless.transforms import Cat, Cos, Select, Sin, TransformedEnv, Unsqueeze
from relayrl.specs import ArraySpec


class PendulumParams(NamedTuple):
    """Physical constants, each `[*B]` (usually broadcast views of one value)."""

    max_speed: torch.Tensor
    max_torque: torch.Tensor
    dt: torch.Tensor
    g: torch.Tensor
    m: torch.Tensor
    l: torch.Tensor  # noqa: E741 (the physics name)


class PendulumState(NamedTuple):
    th: torch.Tensor  # [*B] angle, 0 = upright; not wrapped (Gymnasium does not wrap it)
    thdot: torch.Tensor  # [*B] angular velocity
    step: torch.Tensor  # [*B] int64: steps taken in this episode
    params: PendulumParams


def pendulum_params(g: float = 10.0, m: float = 1.0, l: float = 1.0, dt: float = 0.05,  # noqa: E741
                    max_speed: float = 8.0, max_torque: float = 2.0, dtype: torch.dtype = torch.float32,
                    device: DeviceLike = "cpu") -> PendulumParams:
    """Scalar (shape `()`) params; Gymnasium's defaults. `reset` broadcasts them."""

    def t(v: float) -> torch.Tensor:
        return torch.tensor(v, dtype=dtype, device=device)

    return PendulumParams(t(max_speed), t(max_torque), t(dt), t(g), t(m), t(l))


def angle_normalize(x: torch.Tensor) -> torch.Tensor:
    return ((x + math.pi) % (2 * math.pi)) - math.pi  # floor-mod, as NumPy's %


class Pendulum(StatelessEnv[PendulumState, PendulumParams]):
    """Stateless Pendulum-v1. `params` set the defaults `reset` uses when given none."""

    graph_safe = True  # pure tensor maps; the default params are broadcast once per shape (`_expanded`)

    def __init__(self, params: PendulumParams | None = None, max_episode_steps: int = 200,
                 dtype: torch.dtype = torch.float32, device: DeviceLike = "cpu") -> None:
        self.device = torch.device(device or "cpu")
        self.dtype = dtype
        self.max_episode_steps = max_episode_steps  # 0: never truncate
        self.params = params if params is not None else pendulum_params(dtype=dtype, device=self.device)
        self._default_params: dict[tuple[tuple[int, ...], torch.device], tuple[PendulumParams, PendulumParams]] = {}
        max_speed, max_torque = float(self.params.max_speed.max()), float(self.params.max_torque.max())
        scalar = ArraySpec((), dtype)
        self.observation_spec = {"th": scalar, "thdot": bounded((), dtype, -max_speed, max_speed)}
        self.action_spec = bounded((1,), dtype, -max_torque, max_torque)
        # Worst cost: angle pi, full speed, full torque (Gymnasium's documented reward range).
        worst = math.pi**2 + 0.1 * max_speed**2 + 0.001 * max_torque**2
        self.reward_spec = bounded((), dtype, -worst, 0.0)
        self.done_spec = ArraySpec((), torch.bool)
        # Specs where the state holds tensors (StatelessEnv.state_spec), which the NamedTuples' fields do not say.
        leaf: Any = scalar
        self.state_spec = PendulumState(
            th=leaf, thdot=cast(Any, self.observation_spec["thdot"]), step=cast(Any, bounded((), torch.int64, 0, None)),
            params=PendulumParams(*([leaf] * len(PendulumParams._fields))),
        )

    def reset(self, batch_shape: BatchShape = (), generator: torch.Generator | None = None,
              device: DeviceLike = None, params: PendulumParams | None = None) -> tuple[PendulumState, Obs]:
        shape = as_batch_shape(batch_shape)
        dev = torch.device(device) if device is not None else self.device
        p = self._expanded(params if params is not None else self.params, shape, dev)
        # Gymnasium: uniform(low=-[pi, 1], high=[pi, 1]); th first, then thdot.
        th = uniform(-math.pi, math.pi, shape, generator, dev, self.dtype)
        thdot = uniform(-1.0, 1.0, shape, generator, dev, self.dtype)
        state = PendulumState(th, thdot, torch.zeros(shape, dtype=torch.int64, device=dev), p)
        return state, self.observe(state)

    def _expanded(self, params: PendulumParams, shape: tuple[int, ...], dev: torch.device) -> PendulumParams:
        """`params` broadcast to `shape` on `dev` (views of the scalars, no copy per row). The
        defaults' are made once per shape and reused (batched envs reset every step on a GPU,
        and `tree_where` passes one tensor on both sides through), unless they need grad."""
        cached = self._default_params.get((shape, dev))
        if cached is not None and params is cached[0]:
            return cached[1]
        p = PendulumParams(*(x.to(dev, self.dtype).expand(shape) for x in params))
        if params is self.params and not any(x.requires_grad for x in params):
            self._default_params[(shape, dev)] = (params, p)
        return p

    def step(self, state: PendulumState, action: torch.Tensor) -> StepResult[PendulumState]:
        th, thdot, p = state.th, state.thdot, state.params
        # The torque terms stay in the action's dtype, as NumPy 2 computes them in Gymnasium
        # (float32 action, float64 state): a float64 env then follows Gymnasium to ~1e-12.
        u = action.squeeze(-1)  # [*B, 1] -> [*B]
        max_torque = p.max_torque.to(u.dtype)
        u = torch.clamp(u, -max_torque, max_torque)
        cost = angle_normalize(th) ** 2 + 0.1 * thdot**2 + (0.001 * u**2).to(th.dtype)
        torque = ((3.0 / (p.m * p.l**2)).to(u.dtype) * u).to(th.dtype)
        new_thdot = thdot + (3 * p.g / (2 * p.l) * torch.sin(th) + torque) * p.dt
        new_thdot = torch.clamp(new_thdot, -p.max_speed, p.max_speed)
        new_th = th + new_thdot * p.dt
        step = state.step + 1
        if self.max_episode_steps > 0:
            truncated = step >= self.max_episode_steps
        else:
            truncated = torch.zeros_like(step, dtype=torch.bool)
        new_state = PendulumState(new_th, new_thdot, step, p)
        terminated = torch.zeros_like(truncated)
        return StepResult(new_state, self.observe(new_state), -cost, terminated, truncated)

    def observe(self, state: PendulumState) -> Obs:
        return {"th": state.th, "thdot": state.thdot}


def pendulum_transforms() -> list:
    """The tutorial's transforms giving Gymnasium's observation `[cos th, sin th, thdot]`."""
    return [
        Unsqueeze(("th", "thdot"), dim=-1),  # [*B] -> [*B, 1], so they concatenate
        Cos("th", "cos"),
        Sin("th", "sin"),
        Cat(("cos", "sin", "thdot"), "observation"),  # [*B, 3]
        Select(("observation",)),
    ]


def make_pendulum(max_episode_steps: int = 200, dtype: torch.dtype = torch.float32, device: DeviceLike = "cpu",
                  params: PendulumParams | None = None) -> TransformedEnv:
    """Pendulum with one `observation` entry `[*B, 3]` = `[cos th, sin th, thdot]`, as
    Gymnasium's Pendulum-v1 observes it: the env for RL agents and `train_bptt`."""
    env = Pendulum(params, max_episode_steps, dtype, device)
    return TransformedEnv(env, pendulum_transforms())
