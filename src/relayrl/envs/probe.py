"""What in a user's env will break a run, found before training: one reset and one step of a
fresh copy, compared with the Gymnasium API and the env's own spaces.

Only what relayrl cannot work with is reported (a `step` of 4 values, an observation whose shape
or kind does not fit its space, values that casting to an integer space would change, a reward
that is not a number); what it casts or tolerates without loss (float64 observations of the
right shape, values outside the bounds) is left to Gymnasium's checker, whose findings stay
warnings.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from relayrl.envs.gym import missing_spaces, reset_seeded
from relayrl.errors import UserError


def first_problem(env: gym.Env) -> str | None:
    """The first thing about `env` that will break a run, as a sentence, or None."""
    raw = env.unwrapped  # the API first, below the wrappers (a TimeLimit would fail to unpack it)
    if raw is not env:
        problem = _api_problem(raw)[0]
        if problem is not None:
            return problem
    problem, reset_out, step_out = _api_problem(env)
    if problem is not None:
        return problem
    return (observation_problem(reset_out[0], env.observation_space, "reset()")
            or observation_problem(step_out[0], env.observation_space, "step()") or _reward_problem(step_out[1]))


def _api_problem(env: gym.Env) -> tuple[str | None, Any, Any]:
    """(what is wrong with what reset() and step() return, or None; what they returned)."""
    problem = missing_spaces(env)
    if problem is not None:
        return problem, None, None
    try:
        out = reset_seeded(env, 0)
    except UserError as e:  # the old Gym API's reset(self)
        return str(e), None, None
    if not isinstance(out, tuple) or len(out) != 2:
        what = f"{len(out)} values" if isinstance(out, tuple) else f"a {type(out).__name__}"
        return (f"reset() returned {what}; Gymnasium envs return (obs, info) "
                "(gymnasium.Env.reset: `return obs, {}`)"), out, None
    step = env.step(env.action_space.sample())
    if not isinstance(step, tuple) or len(step) != 5:
        what = f"{len(step)} values" if isinstance(step, tuple) else f"a {type(step).__name__}"
        old = " (the old Gym API's obs, reward, done, info: split done into terminated and truncated)" \
            if isinstance(step, tuple) and len(step) == 4 else ""
        problem = f"step() returned {what}; Gymnasium envs return 5: obs, reward, terminated, truncated, info{old}"
        return problem, out, step
    return None, out, step


def observation_problem(obs: Any, space: gym.Space, method: str) -> str | None:
    """Where `obs` cannot be read as `space` says (shape, structure, a non-numeric kind)."""
    pre = f"the observation from {method}"
    if isinstance(space, gym.spaces.Dict):
        if not isinstance(obs, dict) or set(obs) != set(space.spaces):
            got = sorted(obs) if isinstance(obs, dict) else type(obs).__name__
            return f"{pre} is {got}; observation_space is a Dict with keys {sorted(space.spaces)}"
        for key, sub in space.spaces.items():
            problem = observation_problem(obs[key], sub, f"{method}[{key!r}]")
            if problem is not None:
                return problem
        return None
    if isinstance(space, gym.spaces.Tuple):
        if not isinstance(obs, (tuple, list)) or len(obs) != len(space.spaces):
            return f"{pre} is {_kind(obs)}; observation_space is a Tuple of {len(space.spaces)}"
        for i, (x, sub) in enumerate(zip(obs, space.spaces, strict=True)):
            problem = observation_problem(x, sub, f"{method}[{i}]")
            if problem is not None:
                return problem
        return None
    if space.shape is None:  # a space relayrl does not read as arrays: its own check says so
        return None
    try:
        array = np.asarray(obs)
    except Exception:  # ragged lists and the like
        return f"{pre} is {_kind(obs)}, not an array; observation_space is {space}"
    if array.dtype.kind not in "biuf":
        return f"{pre} has dtype {array.dtype}, not numbers; observation_space is {space}"
    if tuple(array.shape) != tuple(space.shape):
        return (f"{pre} has shape {tuple(array.shape)} but observation_space is {space} "
                f"(shape {tuple(space.shape)}): return arrays of the space's shape, or declare the shape returned")
    return _cast_problem(array, space, pre)


def _cast_problem(array: np.ndarray, space: gym.Space, pre: str) -> str | None:
    """Values an integer space's dtype would change: fractions (frames scaled to [0, 1] in a uint8
    space would train as black) or numbers outside the dtype (wrapped around)."""
    dtype = np.dtype(space.dtype) if space.dtype is not None else None
    if dtype is None or dtype.kind not in "iu" or array.dtype.kind == "b" or not array.size:
        return None
    if array.dtype.kind == "f" and not np.array_equal(array, np.round(array)):
        return (f"{pre} holds {array.dtype} values that are not whole numbers (such as "
                f"{array[array != np.round(array)].flat[0]:g}) but observation_space is {space}, which keeps "
                f"{dtype} integers: declare a float32 Box (frames scaled to [0, 1]: Box(0.0, 1.0, ...)), or "
                "return the integers")
    info = np.iinfo(dtype)
    low, high = array.min(), array.max()
    if low < info.min or high > info.max:
        return (f"{pre} holds {low if low < info.min else high:g}, outside {dtype}'s range [{info.min}, "
                f"{info.max}], but observation_space is {space}: declare a wider dtype, or return values in range")
    return None


def _reward_problem(reward: Any) -> str | None:
    try:
        value = np.asarray(reward, dtype=np.float64)
    except (TypeError, ValueError):
        return f"the reward from step() is {_kind(reward)}; it must be a number"
    if value.shape != ():
        return f"the reward from step() has shape {value.shape}; it must be one number"
    return None


def _kind(x: Any) -> str:
    shape = getattr(x, "shape", None)
    return f"a {type(x).__name__}" + (f" of shape {tuple(shape)}" if shape is not None else "")
