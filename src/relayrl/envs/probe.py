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
from relayrl.envs.observations import kind, observation_problem
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


def _reward_problem(reward: Any) -> str | None:
    try:
        value = np.asarray(reward, dtype=np.float64)
    except (TypeError, ValueError):
        return f"the reward from step() is {kind(reward)}; it must be a number"
    if value.shape != ():
        return f"the reward from step() has shape {value.shape}; it must be one number"
    return None
