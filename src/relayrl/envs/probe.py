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

from relayrl.envs.gym import missing_spaces, reset_problem, reset_seeded, reward_problem, step_problem
from relayrl.envs.observations import observation_problem
from relayrl.errors import UserError
from relayrl.specs import spec_from_space


def first_problem(env: gym.Env) -> str | None:
    """The first thing about `env` that will break a run, as a sentence, or None."""
    if (problem := missing_spaces(env) or _unsupported_space(env)) is not None:  # before the env is stepped
        return problem
    raw = env.unwrapped  # the API first, below the wrappers (a TimeLimit would fail to unpack it)
    if raw is not env:
        problem = _api_problem(raw)[0]
        if problem is not None:
            return problem
    problem, reset_out, step_out = _api_problem(env)
    if problem is not None:
        return problem
    return (observation_problem(reset_out[0], env.observation_space, "reset()")
            or observation_problem(step_out[0], env.observation_space, "step()") or reward_problem(step_out[1]))


def _unsupported_space(env: gym.Env) -> str | None:
    """A space relayrl cannot take (a Dict action space, a Text observation), said before a step
    with a sample of it reaches an env that never handles one."""
    try:
        spec_from_space(env.observation_space, "observation")
        spec_from_space(env.action_space, "action")
    except UserError as e:
        return str(e)
    return None


def _api_problem(env: gym.Env) -> tuple[str | None, Any, Any]:
    """(what is wrong with what reset() and step() return, or None; what they returned)."""
    problem = missing_spaces(env)
    if problem is not None:
        return problem, None, None
    try:
        out = reset_seeded(env, 0)
    except UserError as e:  # the old Gym API's reset(self)
        return str(e), None, None
    problem = reset_problem(out)
    if problem is not None:
        return problem, out, None
    step = env.step(env.action_space.sample())
    return step_problem(step), out, step
