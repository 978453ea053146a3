"""Transforms of a stateless env's outputs and inputs, composed by `TransformedEnv`.

A transform is an object with up to three maps and their spec counterparts; each default is
the identity, so a transform overrides only what it changes:

    forward(obs) -> obs            observations, at reset and at every step
    reward(reward) -> reward       rewards
    inverse(action) -> action      actions, from the caller's action space to the env's
    observation_spec / reward_spec / action_spec: the same maps applied to the specs

`TransformedEnv(env, [t1, t2, t3])` applies forward and reward in list order and inverse in
reverse order (t3 first), so the caller sees t3's action space. The state passes through
untouched: transforms see observations, never the state, so they cannot break `step`'s
purity. They must return new dicts and tensors, not modify their inputs in place (autograd
and callers holding the old dict depend on it).

Writing your own (the TorchRL tutorial's SinTransform):

    class Sin(Transform):
        def forward(self, obs):
            return {**obs, "sin": obs["th"].sin()}

        def observation_spec(self, spec):
            th = spec["th"]
            return {**spec, "sin": bounded(th.shape, th.dtype, -1.0, 1.0)}
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from relayrl.envs.stateless.base import BatchShape, DeviceLike, Obs, ObsSpec, StatelessEnv, StepResult, bounded
from relayrl.specs import ArraySpec


class Transform:
    """Identity on everything; subclasses override the maps they change (see module doc).
    `graph_safe` as `StatelessEnv.graph_safe` says it, for the maps a subclass adds."""

    graph_safe = False

    def forward(self, obs: Obs) -> Obs:
        return obs

    def reward(self, reward: torch.Tensor) -> torch.Tensor:
        return reward

    def inverse(self, action: torch.Tensor) -> torch.Tensor:
        return action

    def observation_spec(self, spec: ObsSpec) -> ObsSpec:
        return spec

    def reward_spec(self, spec: ArraySpec) -> ArraySpec:
        return spec

    def action_spec(self, spec: ArraySpec) -> ArraySpec:
        """The spec callers see, given the spec of the env inside."""
        return spec


def _missing(keys: Sequence[str], spec: ObsSpec, who: str) -> None:
    absent = [k for k in keys if k not in spec]
    if absent:
        raise KeyError(f"{who}: observation has no {absent}; it has {sorted(spec)}")


def _affine_bounds(spec: ArraySpec, scale: np.ndarray, loc: np.ndarray) -> tuple[Any, Any]:
    """Bounds of `x * scale + loc` for x within spec's bounds (a negative scale swaps them)."""
    lo = None if spec.low is None else spec.low * scale + loc
    hi = None if spec.high is None else spec.high * scale + loc
    if lo is None or hi is None:
        return (lo, hi) if np.all(scale > 0) else (None, None)
    return np.minimum(lo, hi), np.maximum(lo, hi)


class Unsqueeze(Transform):
    """Add a size-1 dim at `dim` < 0, counted from the end (batch dims lead, so a negative
    dim means the same place at every batch shape)."""

    graph_safe = True

    def __init__(self, keys: Sequence[str], dim: int = -1) -> None:
        if dim >= 0:
            raise ValueError(f"Unsqueeze: dim must be negative (counted from the end), got {dim}")
        self.keys, self.dim = tuple(keys), dim

    def forward(self, obs: Obs) -> Obs:
        return {**obs, **{k: obs[k].unsqueeze(self.dim) for k in self.keys}}

    def observation_spec(self, spec: ObsSpec) -> ObsSpec:
        _missing(self.keys, spec, "Unsqueeze")
        out = dict(spec)
        for k in self.keys:
            s = spec[k]
            pos = len(s.shape) + 1 + self.dim
            shape = (*s.shape[:pos], 1, *s.shape[pos:])
            out[k] = ArraySpec(shape, s.dtype, None if s.low is None else s.low.reshape(shape),
                               None if s.high is None else s.high.reshape(shape))
        return out


class _Elementwise(Transform):
    """out_key = fn(in_key), bounded to [-1, 1]."""

    graph_safe = True

    fn: Callable[[torch.Tensor], torch.Tensor]

    def __init__(self, in_key: str, out_key: str | None = None) -> None:
        self.in_key, self.out_key = in_key, out_key or in_key

    def forward(self, obs: Obs) -> Obs:
        return {**obs, self.out_key: self.fn(obs[self.in_key])}

    def observation_spec(self, spec: ObsSpec) -> ObsSpec:
        _missing([self.in_key], spec, type(self).__name__)
        s = spec[self.in_key]
        return {**spec, self.out_key: bounded(s.shape, s.dtype, -1.0, 1.0)}


class Sin(_Elementwise):
    fn = staticmethod(torch.sin)


class Cos(_Elementwise):
    fn = staticmethod(torch.cos)


class Cat(Transform):
    """Concatenate entries along their last dim into `out_key`; `delete` drops the inputs."""

    graph_safe = True

    def __init__(self, keys: Sequence[str], out_key: str = "observation", delete: bool = True) -> None:
        self.keys, self.out_key, self.delete = tuple(keys), out_key, delete

    def forward(self, obs: Obs) -> Obs:
        out = {k: v for k, v in obs.items() if not (self.delete and k in self.keys)}
        out[self.out_key] = torch.cat([obs[k] for k in self.keys], dim=-1)
        return out

    def observation_spec(self, spec: ObsSpec) -> ObsSpec:
        _missing(self.keys, spec, "Cat")
        parts = [spec[k] for k in self.keys]
        if any(len(p.shape) == 0 for p in parts) or len({p.shape[:-1] for p in parts}) > 1:
            raise ValueError(f"Cat: shapes {[p.shape for p in parts]} cannot be concatenated on the last dim "
                             "(unsqueeze scalars first)")
        dtype = functools.reduce(torch.promote_types, [p.dtype for p in parts])
        shape = (*parts[0].shape[:-1], sum(p.shape[-1] for p in parts))

        def side(name: str) -> np.ndarray | None:
            vals = [getattr(p, name) for p in parts]
            if all(v is None for v in vals):
                return None
            if any(v is None for v in vals):
                fill = -np.inf if name == "low" else np.inf  # one unbounded part: mark it so
                vals = [np.full(p.shape, fill) if v is None else v for p, v in zip(parts, vals, strict=True)]
            return np.concatenate(vals, axis=-1)

        out = {k: v for k, v in spec.items() if not (self.delete and k in self.keys)}
        out[self.out_key] = ArraySpec(shape, dtype, side("low"), side("high"))
        return out


class Select(Transform):
    """Keep only `keys`."""

    graph_safe = True

    def __init__(self, keys: Sequence[str]) -> None:
        self.keys = tuple(keys)

    def forward(self, obs: Obs) -> Obs:
        return {k: obs[k] for k in self.keys}

    def observation_spec(self, spec: ObsSpec) -> ObsSpec:
        _missing(self.keys, spec, "Select")
        return {k: spec[k] for k in self.keys}


class ObservationNorm(Transform):
    """`(x - loc) / scale` on one entry, fixed loc and scale (broadcast to the element shape)."""

    def __init__(self, key: str, loc: float | torch.Tensor = 0.0, scale: float | torch.Tensor = 1.0) -> None:
        self.key = key
        self.loc = torch.as_tensor(loc, dtype=torch.float64)
        self.scale = torch.as_tensor(scale, dtype=torch.float64)

    def forward(self, obs: Obs) -> Obs:
        x = obs[self.key]
        return {**obs, self.key: (x - self.loc.to(x.device, x.dtype)) / self.scale.to(x.device, x.dtype)}

    def observation_spec(self, spec: ObsSpec) -> ObsSpec:
        _missing([self.key], spec, type(self).__name__)
        s = spec[self.key]
        loc = np.broadcast_to(self.loc.numpy(), s.shape)
        scale = np.broadcast_to(self.scale.numpy(), s.shape)
        low, high = _affine_bounds(s, 1.0 / scale, -loc / scale)
        return {**spec, self.key: ArraySpec(s.shape, s.dtype, low, high)}


class RunningObservationNorm(ObservationNorm):
    """ObservationNorm whose loc/scale are the running mean/std of every batch it has seen
    while `update` is True (Welford's parallel update, stats kept in float64).

    The statistics are this transform's own mutable state, outside the env state: freeze them
    (`update = False`) for evaluation, and save them with `state_dict()`. Its spec is unbounded
    since the statistics move."""

    def __init__(self, key: str, shape: tuple[int, ...] = (), eps: float = 1e-8) -> None:
        super().__init__(key, torch.zeros(shape, dtype=torch.float64), torch.ones(shape, dtype=torch.float64))
        self.count = 0.0
        self.m2 = torch.zeros(shape, dtype=torch.float64)
        self.eps, self.update = eps, True

    def forward(self, obs: Obs) -> Obs:
        if self.update:
            x = obs[self.key].detach()
            flat = x.reshape(-1, *self.loc.shape).to("cpu", torch.float64)  # [N, *element]
            n, mean = flat.shape[0], flat.mean(0)
            delta, total = mean - self.loc, self.count + flat.shape[0]
            self.m2 = self.m2 + ((flat - mean) ** 2).sum(0) + delta**2 * self.count * n / total
            self.loc = self.loc + delta * n / total
            self.count = total
            self.scale = (self.m2 / max(self.count, 1.0)).sqrt().clamp_min(self.eps)
        return super().forward(obs)

    def observation_spec(self, spec: ObsSpec) -> ObsSpec:
        _missing([self.key], spec, type(self).__name__)
        s = spec[self.key]
        return {**spec, self.key: ArraySpec(s.shape, s.dtype)}

    def state_dict(self) -> dict[str, Any]:
        return {"loc": self.loc.clone(), "scale": self.scale.clone(), "m2": self.m2.clone(), "count": self.count}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.loc, self.scale, self.m2 = state["loc"].clone(), state["scale"].clone(), state["m2"].clone()
        self.count = float(state["count"])


class RewardScale(Transform):
    """`reward * scale + loc`."""

    graph_safe = True

    def __init__(self, scale: float, loc: float = 0.0) -> None:
        self.scale, self.loc = scale, loc

    def reward(self, reward: torch.Tensor) -> torch.Tensor:
        return reward * self.scale + self.loc

    def reward_spec(self, spec: ArraySpec) -> ArraySpec:
        low, high = _affine_bounds(spec, np.asarray(self.scale), np.asarray(self.loc))
        return ArraySpec(spec.shape, spec.dtype, low, high)


class RescaleAction(Transform):
    """Callers act in [low, high] (default [-1, 1]); `inverse` maps affinely onto the env's
    bounded action range, e.g. a tanh policy's output onto Pendulum's [-2, 2]."""

    def __init__(self, low: float = -1.0, high: float = 1.0) -> None:
        self.low, self.high = low, high

    def action_spec(self, spec: ArraySpec) -> ArraySpec:
        if spec.low is None or spec.high is None:
            raise ValueError("RescaleAction needs a bounded action spec")
        self._env_low = torch.as_tensor(spec.low, dtype=spec.dtype)  # [*act_shape]
        self._env_high = torch.as_tensor(spec.high, dtype=spec.dtype)
        return bounded(spec.shape, spec.dtype, self.low, self.high)

    def inverse(self, action: torch.Tensor) -> torch.Tensor:
        lo, hi = self._env_low.to(action.device), self._env_high.to(action.device)
        return lo + (action - self.low) * ((hi - lo) / (self.high - self.low))


class TransformedEnv(StatelessEnv):
    """`env` seen through `transforms` (see the module doc for the order). Itself a
    StatelessEnv with the same state, so transformed envs nest and `check_env` applies."""

    def __init__(self, env: StatelessEnv, transforms: Sequence[Transform]) -> None:
        self.env, self.transforms = env, list(transforms)
        self.device = env.device
        self.state_spec, self.done_spec = env.state_spec, env.done_spec
        obs_spec, reward_spec, action_spec = env.observation_spec, env.reward_spec, env.action_spec
        for t in self.transforms:
            obs_spec = t.observation_spec(dict(obs_spec))
            reward_spec = t.reward_spec(reward_spec)
        for t in reversed(self.transforms):  # the last transform faces the caller's actions
            action_spec = t.action_spec(action_spec)
        self.observation_spec, self.reward_spec, self.action_spec = obs_spec, reward_spec, action_spec

    def append(self, transform: Transform) -> TransformedEnv:
        """A new TransformedEnv with `transform` added last."""
        return TransformedEnv(self.env, [*self.transforms, transform])

    @property
    def base_env(self) -> StatelessEnv:
        return self.env.base_env

    @property
    def graph_safe(self) -> bool:  # type: ignore[override]
        return self.env.graph_safe and all(t.graph_safe for t in self.transforms)

    def _obs(self, obs: Obs) -> Obs:
        for t in self.transforms:
            obs = t.forward(obs)
        return obs

    def reset(self, batch_shape: BatchShape = (), generator: torch.Generator | None = None,
              device: DeviceLike = None, params: Any = None) -> tuple[Any, Obs]:
        state, obs = self.env.reset(batch_shape, generator, device, params)
        return state, self._obs(obs)

    def step(self, state: Any, action: torch.Tensor) -> StepResult:
        for t in reversed(self.transforms):
            action = t.inverse(action)
        out = self.env.step(state, action)
        reward = out.reward
        for t in self.transforms:
            reward = t.reward(reward)
        return StepResult(out.state, self._obs(out.obs), reward, out.terminated, out.truncated)

    def observe(self, state: Any) -> Obs:
        return self._obs(self.env.observe(state))
