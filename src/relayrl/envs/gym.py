"""Gymnasium envs as a batched env (made by the factories of envs/resolve.py).

We step the copies ourselves rather than through `gymnasium.vector.SyncVectorEnv` because we
need the true final observation of an episode as a plain array (`next_obs`) beside the reset
observation (`obs`); Gymnasium's vector autoreset modes either delay the reset by one step
(a step whose transition must be dropped) or put the final observation in per-env info dicts.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import pickle
from collections.abc import Callable
from typing import Any, SupportsFloat, cast

import gymnasium as gym
import numpy as np
import torch
from gymnasium.utils import EzPickle

from relayrl.core import BatchedEnv
from relayrl.envs.observations import kind, observation_problem
from relayrl.envs.pixels import frame_stack_of
from relayrl.envs.resolve import EnvFn
from relayrl.errors import UserError, note_where, one_line
from relayrl.specs import (
    ArraySpec,
    PackedSpec,
    Spec,
    describe,
    env_numpy_dtype,
    flat_action,
    numpy_dtype,
    spec_from_space,
    value_limit,
)
from relayrl.types import EpisodeInfo, StepOutput

# What writing an observation that does not fit its space raises (packing a Dict without one of
# its keys: the pack's UserError, which names neither the copy nor the method)
_UNFIT = (ValueError, TypeError, KeyError, OverflowError, UserError)


def episode_info(keys: tuple[str, ...], num_envs: int, ended: list[int],
                 info_of: Callable[[int], dict]) -> EpisodeInfo | None:
    """`env.info_keys` values from the last info of each episode that ended (None if none did).

    A key missing at an episode's end is a config error, not a silent NaN: a typo in
    `info_keys` would otherwise log nothing for a whole run.
    """
    if not keys or not ended:
        return None
    out = {k: np.full(num_envs, np.nan) for k in keys}
    for i in ended:
        info = info_of(i)
        if not isinstance(info, dict):
            raise UserError(f"env.info_keys: the env's info at an episode's end is {type(info).__name__} "
                            f"{one_line(str(info))}, not a dict: return a dict from step(), or leave env.info_keys "
                            "empty")
        for k in keys:
            if k not in info:
                raise UserError(f"env.info_keys: {k!r} is not in the env's info at an episode's end; "
                                f"keys there: {sorted(info)}")
            try:
                out[k][i] = float(info[k])
            except (TypeError, ValueError):
                # an array of one value (np.array([x]), a simulator's habit) reads as a number: say why not
                shape = getattr(info[k], "shape", ())
                hint = f" (an array of shape {tuple(shape)}: give one number, such as x.item())" if shape else ""
                raise UserError(f"env.info_keys: info[{k!r}] = {one_line(repr(info[k]), 80)} is not a number{hint}") \
                    from None
    return out


def env_snapshot(env: gym.Env) -> bytes | None:
    """The env's whole state (dynamics, episode step count, RNGs) pickled, or None for envs
    that cannot be pickled (`snapshot_problem` says why)."""
    return _snapshot(env)[0]


def snapshot_problem(env: gym.Env) -> str | None:
    """Why `env_snapshot` gives None for `env`, in words for the log; None where it does not."""
    return _snapshot(env)[1]


def _snapshot(env: gym.Env) -> tuple[bytes | None, str | None]:
    """The pickle, or why there is none: a simulator handle (pybullet's), an env that opts out
    by raising TypeError from `__getstate__`, a wrapper holding a lambda, or a layer whose pickle
    keeps only its constructor's arguments (Gymnasium's EzPickle: the MuJoCo and Box2D envs
    come back as new, un-reset simulators, not mid-episode)."""
    layer: Any = env
    while layer is not None:
        if type(layer).__getstate__ is EzPickle.__getstate__:
            return None, (f"{type(layer).__name__} pickles only its constructor's arguments (Gymnasium's EzPickle, "
                          "as MuJoCo's and Box2D's envs), not its state mid-episode")
        layer = layer.env if isinstance(layer, gym.Wrapper) else None
    try:
        return pickle.dumps(env), None
    except Exception as e:  # pickling runs arbitrary user code: any failure means "not checkpointable"
        why = f"the env cannot be pickled mid-episode: {one_line(str(e) or type(e).__name__, 160)}"
        if "__main__" in str(e):  # a worker process started by spawn rebuilt the script's class by value
            why += ("; a class defined in the main script or a notebook is not the same object in a worker "
                    "process started by spawn (macOS, Windows): define the env in a module of its own")
        return None, why


class BatchEnvBase(BatchedEnv):
    """Specs and flags shared by the in-process and the worker-process batched envs."""

    def _init_specs(self, num_envs: int, observation_space: gym.Space, action_space: gym.Space,
                    time_limit_terminates: bool, frame_stack: int = 1) -> None:
        self.num_envs = num_envs
        self.observation_spec: Spec = spec_from_space(observation_space, "observation")
        if frame_stack > 1 and isinstance(self.observation_spec, ArraySpec):
            # Stacked frames (FrameStackObservation): the replay stores one frame per step.
            self.observation_spec = dataclasses.replace(self.observation_spec, frame_stack=frame_stack)
        self.action_spec: Spec = spec_from_space(action_space, "action")
        self._env_action_shape: tuple[int, ...] | None = None  # a Box action of rank != 1: reshaped to it
        if isinstance(action_space, gym.spaces.Box) and isinstance(self.action_spec, ArraySpec):
            self.action_spec = flat_action(self.action_spec)
            self._env_action_shape = self.action_spec.env_shape
        self._obs_dtype = numpy_dtype(self.observation_spec)
        # actions are given in the space's own dtype (an env may check action_space.contains)
        self._env_action_dtype = env_numpy_dtype(self.action_spec) if isinstance(self.action_spec, ArraySpec) else None
        # relayrl's policies keep their float32 actions inside the float32 bounds; where the env's
        # dtype is another, the cast can land a rounding step past its own bounds (0.3 in float32
        # is 0.30000001192 in float64): those actions are clipped again, in the env's dtype
        # (np.dtype(None) is float64: `in (None, ...)` would match it)
        other = self._env_action_dtype is not None and self._env_action_dtype != np.float32
        self._action_bounds = box_bounds(action_space) if other else None
        # Dict / Tuple observations travel as packed byte rows (specs.PackedSpec); None: as they are
        self._pack = self.observation_spec.pack if isinstance(self.observation_spec, PackedSpec) else None
        self._discrete = isinstance(action_space, gym.spaces.Discrete)
        # Discrete, MultiDiscrete and MultiBinary observations (and Dict / Tuple entries) index
        # one-hots: (entry or None for the whole row, the values' exclusive limit) of each.
        spec = self.observation_spec
        parts = [(f, f.spec) for f in spec.fields] if isinstance(spec, PackedSpec) else [(None, spec)]
        self._obs_limits = [(f, limit) for f, s in parts if (limit := value_limit(s)) is not None]
        # Old gym (and so the TF-Agents tutorials) reported a time-limit cut as `done`, a
        # termination: targets do not bootstrap through it. Some presets reproduce that.
        self.time_limit_terminates = time_limit_terminates
        self.info_keys: tuple[str, ...] = ()  # set by make_env: info values logged per episode

    def _check_observations(self, obs: np.ndarray, where: str = "step") -> None:
        """One line for observations [B, ...] outside the env's own Discrete / MultiDiscrete /
        MultiBinary space or entry (a one-hot past its end would be an index error deep in a network)."""
        for f, high in self._obs_limits:
            values = obs if f is None else obs[:, f.offset:f.offset + f.nbytes].view(numpy_dtype(f.spec))
            values = values.reshape(len(obs), -1)  # [B, entries]
            out = ((values < 0) | (values >= np.asarray(high).reshape(-1))).any(axis=1)
            if out.any():
                row = values[int(np.flatnonzero(out)[0])]
                bad = row[0] if row.size == 1 else row
                entry = "" if f is None else f"[{f.key!r}]"
                space = describe(self.observation_spec if f is None else f.spec)
                raise UserError(f"the env's {where} returned observation{entry} {bad.tolist()}, outside its own "
                                f"observation space {space}")

    def _actions(self, action: torch.Tensor) -> np.ndarray:
        """A step's actions as a NumPy array, one row per copy (anything else is refused)."""
        act = action.numpy()
        if act.shape[:1] != (self.num_envs,):
            raise ValueError(f"actions for {act.shape[0] if act.ndim else 'no'} copies, "
                             f"but this env has {self.num_envs}")
        want = self.action_spec.shape
        if act.shape[1:] != want and act.shape[1:] != self._env_action_shape:  # flat, or the env's shape
            # [B, 1] for a scalar action (argmax with keepdim) and [B] for a one-dim Box(1,)
            # are the same actions; any other shape is a mistake worth one clear line.
            if _drop_trailing_ones(act.shape[1:]) != _drop_trailing_ones(want):
                raise ValueError(f"actions of shape {tuple(act.shape)}, but this env takes {(self.num_envs, *want)}: "
                                 f"{self.num_envs} copies of action shape {want}")
            act = act.reshape(self.num_envs, *want)
        if self._env_action_dtype is not None and act.dtype != self._env_action_dtype:
            act = act.astype(self._env_action_dtype)
        act = act if self._env_action_shape is None else act.reshape(self.num_envs, *self._env_action_shape)
        if self._action_bounds is not None:  # a new array (astype's, or the policy's tensor a rollout keeps)
            act = np.clip(act, *self._action_bounds)
        return act


def box_bounds(space: gym.Space) -> tuple[np.ndarray, np.ndarray] | None:
    """A Box action space's (low, high) in its own dtype and shape; None for other spaces and
    for a Box unbounded on every side (nothing to clip to)."""
    if not isinstance(space, gym.spaces.Box) or not (space.bounded_below.any() or space.bounded_above.any()):
        return None
    return np.asarray(space.low, space.dtype), np.asarray(space.high, space.dtype)


def _drop_trailing_ones(shape: tuple[int, ...]) -> tuple[int, ...]:
    while shape and shape[-1] == 1:
        shape = shape[:-1]
    return shape



def missing_spaces(env: gym.Env) -> str | None:
    """A sentence naming the space an env does not define, or None."""
    for name in ("observation_space", "action_space"):
        if not isinstance(getattr(env, name, None), gym.Space):
            return (f"the env has no {name} (a gymnasium.spaces.Space): set self.{name} in its __init__ "
                    "(gymnasium.Env's API)")
    return None


def reset_seeded(env: gym.Env, seed: int | None) -> tuple[Any, Any]:
    """`env.reset(seed=seed)`; one line for an env whose reset takes no seed (the old Gym API) or
    no options (which Gymnasium's wrappers, a TimeLimit's, pass on)."""
    try:
        return env.reset(seed=seed)
    except TypeError as e:
        missing = next((k for k in ("seed", "options") if f"unexpected keyword argument '{k}'" in str(e)), None)
        if missing is None or _reset_takes(env, missing):  # then it came from inside the env's reset
            raise
        raise UserError(f"the env's reset() takes no {missing}: Gymnasium envs define reset(self, *, seed=None, "
                        "options=None), call super().reset(seed=seed) and return (obs, info)") from None


def _reset_takes(env: gym.Env, name: str) -> bool:
    """Whether the env's own reset takes `name`= (a TypeError about it then came from inside it)."""
    try:
        params = inspect.signature(env.unwrapped.reset).parameters.values()
    except (TypeError, ValueError):  # no signature to read (a builtin): assume the Gymnasium API
        return True
    return any(p.name == name or p.kind is inspect.Parameter.VAR_KEYWORD for p in params)


def reset_problem(out: Any, method: str = "reset()") -> str | None:
    """What is wrong with what an env's reset returned (the Gymnasium API's (obs, info)), or None."""
    if isinstance(out, tuple) and len(out) == 2:
        return None
    what = f"{len(out)} values" if isinstance(out, tuple) else f"a {type(out).__name__}"
    return f"{method} returned {what}; Gymnasium envs return (obs, info) (gymnasium.Env.reset: `return obs, {{}}`)"


def step_problem(out: Any, method: str = "step()") -> str | None:
    """What is wrong with what an env's step returned (the Gymnasium API's 5 values), or None."""
    if isinstance(out, tuple) and len(out) == 5:
        return None
    what = f"{len(out)} values" if isinstance(out, tuple) else f"a {type(out).__name__}"
    old = " (the old Gym API's obs, reward, done, info: split done into terminated and truncated)" \
        if isinstance(out, tuple) and len(out) == 4 else ""
    return f"{method} returned {what}; Gymnasium envs return 5: obs, reward, terminated, truncated, info{old}"


def reward_problem(reward: Any, method: str = "step()") -> str | None:
    """What is wrong with a reward an env's step returned (it must be one number), or None."""
    if reward is None or isinstance(reward, (str, bytes)):  # NumPy reads None as NaN, "1.0" as 1.0
        return f"the reward from {method} is {reward!r}; it must be a number"
    try:
        value = np.asarray(reward, dtype=np.float64)
    except (TypeError, ValueError):
        return f"the reward from {method} is {kind(reward)}; it must be a number"
    if value.shape != ():
        return f"the reward from {method} has shape {value.shape}; it must be one number"
    return None


class _StepCap(gym.Wrapper):
    """A time limit that counts the episodes it ended (`cuts`): one the env ended itself, at
    the cap's step too, is not one, so an env that ends its own episodes is never told about it."""

    def __init__(self, env: gym.Env, max_episode_steps: int) -> None:
        super().__init__(env)
        self.max_episode_steps, self.steps, self.cuts = max_episode_steps, 0, 0

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        self.steps = 0
        return self.env.reset(**kwargs)

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        out = self.env.step(action)
        try:
            obs, reward, terminated, truncated, info = out
        except (TypeError, ValueError):  # off the Gymnasium API: GymBatchEnv.step_into says so in one line
            return out
        self.steps += 1
        cut = self.steps >= self.max_episode_steps and not (terminated or truncated)
        self.cuts += cut
        return obs, reward, terminated, truncated or cut, info


class GymBatchEnv(BatchEnvBase):
    """`num_envs` Gymnasium envs stepped in this process, as one batched env."""

    def __init__(self, env_fns: list[EnvFn], time_limit_terminates: bool = False, first_copy: int = 0) -> None:
        if not env_fns:
            raise UserError("env.num_envs must be >= 1")
        self.envs = []
        try:
            for fn in env_fns:
                self.envs.append(fn())
            problem = missing_spaces(self.envs[0])
            if problem is not None:
                raise UserError(problem)
        except BaseException:
            self.close()  # the copies already made (their windows, files, processes) go with the failure
            raise
        self.capped_at = 0  # cap_episodes: the step cap put on an env without a time limit
        # The batch index of copy 0 here: an async worker steps a slice of a larger batch, and
        # its messages name the copy by the batch's index, as the main process's do.
        self.first_copy = first_copy
        self._caps: list[_StepCap] = []
        first = self.envs[0]
        self._init_specs(len(self.envs), first.observation_space, first.action_space, time_limit_terminates,
                         frame_stack_of(first))
        # An integer space's stored dtype: an observation whose write into it may change values
        # (fractions cast to 0, numbers outside it wrapped) is checked first (`_kept`); a Dict /
        # Tuple's integer entries are checked by `pack`.
        self._int_obs = self._obs_dtype if self._pack is None and self._obs_dtype.kind in "iu" else None
        self._safe_casts: dict[np.dtype, bool] = {}  # per observation dtype: whether the write keeps every value
        # An array observation's shape, checked before its row is written: NumPy would broadcast a
        # scalar or a [1, n] row into [n] without a word (a Dict / Tuple's entries: `pack` checks)
        self._obs_shape = None if self._pack is not None else tuple(self.observation_spec.shape)

    @property
    def time_limited(self) -> bool:
        """Whether a TimeLimit anywhere in the copies' wrappers ends their episodes (else only the env does)."""
        e: Any = self.envs[0]
        while e is not None:
            if isinstance(e, gym.wrappers.TimeLimit):
                return True
            e = getattr(e, "env", None)
        return False

    def cap_episodes(self, max_episode_steps: int) -> None:
        """Cut every copy's episodes at `max_episode_steps` (for an env without a time limit)."""
        self._caps = [_StepCap(env, max_episode_steps) for env in self.envs]
        self.envs = list(self._caps)
        self.capped_at = max_episode_steps

    @property
    def episodes_cut(self) -> int:
        """Episodes `cap_episodes`'s cap has ended so far."""
        return sum(cap.cuts for cap in self._caps)

    def get_state(self) -> list[bytes] | None:
        """Every copy's state, for checkpoints that resume mid-episode; None if any copy
        cannot be pickled (a resumed run then starts new episodes)."""
        states = [env_snapshot(env) for env in self.envs]
        return None if any(s is None for s in states) else states  # type: ignore[return-value]

    def state_problem(self) -> str | None:
        """Why `get_state` gives None (the first copy's reason), or None where it does not."""
        return next((why for env in self.envs if (why := snapshot_problem(env)) is not None), None)

    def set_state(self, states: list[bytes]) -> None:
        for env in self.envs:
            env.close()
        self.envs = [pickle.loads(s) for s in states]

    def reset(self, seed: int | None = None) -> torch.Tensor:
        obs = []
        for i, env in enumerate(self.envs):
            o = self._reset_obs(i, functools.partial(reset_seeded, env, None if seed is None else seed + i))
            if seed is not None:
                env.action_space.seed(seed + i)
            try:
                obs.append(o if self._pack is None else self._pack(o))
                self._check_shape(o)
            except _UNFIT as e:
                raise self._unfit(o, i, "reset()", e) from None
        rows = np.stack(obs).astype(self._obs_dtype, copy=False)
        self._check_observations(rows, "reset")
        return torch.from_numpy(rows)

    def step(self, action: torch.Tensor) -> StepOutput:
        b = self.num_envs
        act = self._actions(action)
        next_obs = np.empty((b, *self.observation_spec.shape), self._obs_dtype)
        reward, terminated, truncated = np.empty(b, np.float32), np.empty(b, np.bool_), np.empty(b, np.bool_)
        obs, info = self.step_into(act, next_obs, reward, terminated, truncated)
        self._check_observations(next_obs)
        if obs is not next_obs:
            self._check_observations(obs, "reset")
        return StepOutput(torch.from_numpy(next_obs), torch.from_numpy(reward), torch.from_numpy(terminated),
                          torch.from_numpy(truncated), torch.from_numpy(obs), info)

    def step_into(self, action: np.ndarray, next_obs: np.ndarray, reward: np.ndarray, terminated: np.ndarray,
                  truncated: np.ndarray, reset_obs: np.ndarray | None = None) -> tuple[np.ndarray, EpisodeInfo | None]:
        """Step every copy, writing the results into the given [num_envs, ...] arrays (the
        worker processes pass shared memory). Copies whose episode ended are reset: their
        reset observations go into `reset_obs` (its other rows untouched), or, when it is None,
        into a copy of `next_obs`. Returns that obs array (`next_obs` itself if none ended)
        and the ended episodes' `info_keys` values."""
        # tolist() gives Python ints for discrete actions: what Gymnasium envs compare against.
        # A scalar Box's row is a 0-d array (`[i, ...]`), not a NumPy scalar: Box.contains and
        # users' envs take arrays.
        # Each env is given its own copy (as Gymnasium's vector envs and SB3 do): an env or an
        # ActionWrapper writing into its action (`a *= 2`) leaves the stored action as taken.
        if self._discrete:
            actions: Any = action.tolist()
        else:
            action = action.copy()
            actions = action if action.ndim > 1 else [action[i, ...] for i in range(action.shape[0])]
        ended = []
        infos: dict[int, dict] = {}
        pack, int_obs, shape = self._pack, self._int_obs, self._obs_shape
        for i, env in enumerate(self.envs):
            try:
                out = env.step(actions[i])
            except Exception as e:
                note_where(e, f"by {self._method('step()', i)}")
                raise
            try:  # the start's check (env.check) finds an env off the API; without it, or mid-run, this does
                o, r, term, trunc, info = out
            except (TypeError, ValueError):
                raise UserError(step_problem(out, self._method("step()", i))) from None
            try:
                if shape is not None and getattr(o, "shape", None) != shape:  # an array's: an attribute read
                    self._check_shape(o)
                next_obs[i] = o if pack is None else pack(o)
                if int_obs is not None and getattr(o, "dtype", None) != int_obs and not self._kept(o):
                    self._check_cast(o, i, "step()")
            except _UNFIT as e:  # observations that change mid-run
                raise self._unfit(o, i, "step()", e) from None
            try:
                reward[i] = r
                if r.__class__ is not float and (r is None or isinstance(r, (str, bytes))):  # written as NaN, or parsed
                    raise TypeError
            except (TypeError, ValueError):
                method = self._method("step()", i)
                said = reward_problem(r, method) or f"the reward from {method} is {r!r}; it must be a number"
                raise UserError(said) from None
            if self.time_limit_terminates:
                term, trunc = term or trunc, False
            terminated[i] = term
            truncated[i] = trunc
            if term or trunc:
                ended.append(i)
                infos[i] = info
        obs = next_obs if reset_obs is None else reset_obs  # shared unless some copy is reset
        if ended and reset_obs is None:
            # Copy only once every row of next_obs is written (copying at the first reset
            # would carry unwritten rows of later copies into obs).
            obs = next_obs.copy()
        for i in ended:
            o = self._reset_obs(i, self.envs[i].reset)
            try:
                self._check_shape(o)
                obs[i] = o if pack is None else pack(o)
            except _UNFIT as e:
                raise self._unfit(o, i, "reset()", e) from None
        return obs, episode_info(self.info_keys, len(self.envs), ended, infos.__getitem__)

    def _check_shape(self, obs: Any) -> None:
        """ValueError for an array observation of another shape than its space's."""
        if self._obs_shape is not None and np.shape(obs) != self._obs_shape:
            raise ValueError(f"shape {tuple(np.shape(obs))}, not the space's {self._obs_shape}")

    def _method(self, method: str, i: int) -> str:
        """`method` of copy i, named by its index in the whole batch (see first_copy)."""
        return f"{method} of env copy {self.first_copy + i}"

    def _reset_obs(self, i: int, reset: Callable[[], Any]) -> Any:
        """The observation `reset()` of copy i returns; one line where it returns no (obs, info)
        (`reset()[0]` of a bare observation would be its first entry), and the env's own
        exception names the copy."""
        try:
            out = reset()
        except Exception as e:
            note_where(e, f"by {self._method('reset()', i)}")
            raise
        problem = reset_problem(out, self._method("reset()", i))
        if problem is not None:
            raise UserError(problem)
        if self._int_obs is not None and not self._kept(out[0]):
            self._check_cast(out[0], i, "reset()")
        return out[0]

    def _kept(self, obs: Any) -> bool:
        """Whether writing `obs` into the integer rows keeps every value, known without reading
        them: a Python int (a Discrete index; `_check_observations` checks its range) or an array
        whose dtype casts safely (int32 into the int64 kept, uint8 into uint8)."""
        if isinstance(obs, int):
            return True
        dtype = getattr(obs, "dtype", None)
        if not isinstance(dtype, np.dtype):
            return False  # a list, a tensor: its values are read
        safe = self._safe_casts.get(dtype)
        if safe is None:
            safe = self._safe_casts[dtype] = bool(np.can_cast(dtype, self._obs_dtype, "safe"))
        return safe

    def _check_cast(self, obs: Any, i: int, method: str) -> None:
        """One line where copy i's observation holds values its integer space's dtype would
        change (the start's check saw ones it keeps)."""
        problem = observation_problem(obs, self.envs[i].observation_space, self._method(method, i))
        if problem is not None:
            raise UserError(problem)

    def _unfit(self, obs: Any, i: int, method: str, error: Exception) -> UserError:
        """One line for an observation that does not fit the env's space, met mid-run (the
        start's check saw fitting ones)."""
        where = self._method(method, i)
        problem = observation_problem(obs, self.envs[i].observation_space, where)
        return UserError(problem or f"the observation from {where} does not fit its observation "
                                    f"space {self.envs[i].observation_space} ({type(error).__name__}: {error})")

    def render(self) -> np.ndarray | None:
        # An rgb_array frame (the mode the video command makes envs in), or None without a render mode
        return cast("np.ndarray | None", self.envs[0].render())

    def close(self) -> None:
        """Every copy closed (its window, files, processes), also where one's own close() raises:
        the first such error is raised after the rest are closed."""
        failure: Exception | None = None
        for env in self.envs:
            try:
                env.close()
            except Exception as e:
                failure = failure or e
        if failure is not None:
            raise failure
