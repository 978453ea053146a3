"""Where an observation cannot be read as its Gymnasium space says: the shape, the structure of a
Dict or Tuple, a kind that is not numbers, or values that casting to an integer space would
change. Asked by the env probe before a run (`envs.probe`) and by the batched env when an
observation stops fitting mid-run (`envs.gym`)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np


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
            return f"{pre} is {kind(obs)}; observation_space is a Tuple of {len(space.spaces)}"
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
        return f"{pre} is {kind(obs)}, not an array; observation_space is {space}"
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


def kind(x: Any) -> str:
    shape = getattr(x, "shape", None)
    return f"a {type(x).__name__}" + (f" of shape {tuple(shape)}" if shape is not None else "")
