"""Average return of a policy over whole episodes, run as one batch of env copies."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from relayrl.arrays import to_numpy
from relayrl.core import BatchedEnv
from relayrl.envs import make_env
from relayrl.envs.ale_vector import unsupported_kwargs
from relayrl.envs.gym import GymBatchEnv
from relayrl.envs.resolve import EnvFn
from relayrl.errors import NonFiniteError, UserError, note_where
from relayrl.specs import describe as describe_spec
from relayrl.specs import spec_state
from relayrl.training.finite import describe

EVAL_BATCH = 16  # eval episodes run as one batch of at most this many env copies
# Evaluation episodes of an env without a time limit (and no env.max_episode_steps) end here, so
# that an evaluation of a policy that never reaches a terminal state ends: a user's env, or a
# registered one such as CliffWalking-v1. ALE's games are left alone: they end their episodes
# at their own frame cap, and a game of Pong outlasts 1,000 steps.
EVAL_MAX_EPISODE_STEPS = 1_000


def make_eval_env(env_id: str, episodes: int, max_episode_steps: int = 0,
                  device: str | torch.device = "cpu", info_keys: tuple[str, ...] | list[str] = (),
                  kwargs: dict[str, Any] | None = None, wrappers: tuple[str, ...] | list[str] = (),
                  factory: EnvFn | None = None, vectorization: str = "sync", num_workers: int = 0
                  ) -> BatchedEnv:
    """min(episodes, EVAL_BATCH) copies, their episodes capped where the env has no time limit.
    `vectorization` and `num_workers` are training's: "ale" steps the copies in ale-py's C++
    threads (they give the Gymnasium path's frames: tests/test_ale_vector.py), since an evaluation
    of long Atari games one copy after another takes a large share of a fast run; except where
    the kwargs need the Gymnasium path, or `info_keys` are asked for (ale-py's info at an episode's
    end already describes the next one). Anything else evaluates in this process (worker
    processes would outlive their use)."""
    ale = (vectorization == "ale" and not unsupported_kwargs(kwargs) and not info_keys and not wrappers
           and factory is None)
    env = make_env(env_id, min(episodes, EVAL_BATCH), max_episode_steps, device=device, info_keys=info_keys,
                   kwargs=kwargs, wrappers=wrappers, factory=factory, vectorization="ale" if ale else "sync",
                   num_workers=num_workers if ale else 0)
    cap_untimed(env)
    return env


def check_same_spaces(eval_env: BatchedEnv, env: BatchedEnv, eval_kwargs: dict[str, Any]) -> None:
    """One line where eval.env_kwargs give evaluation envs other spaces than training's (the
    policy takes the training env's)."""
    for kind, got, want in (("observation", eval_env.observation_spec, env.observation_spec),
                            ("action", eval_env.action_spec, env.action_spec)):
        if spec_state(got) != spec_state(want):
            raise UserError(f"eval.env_kwargs {eval_kwargs} give evaluation envs {kind}s "
                            f"{describe_spec(got)}, but the training envs' are {describe_spec(want)}: the policy "
                            f"takes the training env's; leave out the keys that change the {kind} space")


def cap_untimed(env: BatchedEnv, max_episode_steps: int = 0) -> None:
    """Cut the episodes of an env without a time limit, so that an evaluation ends: at
    `max_episode_steps`, or (0) at EVAL_MAX_EPISODE_STEPS unless it is an ALE game."""
    if not isinstance(env, GymBatchEnv) or env.time_limited or env.capped_at:
        return
    if max_episode_steps > 0:
        env.cap_episodes(max_episode_steps)
    elif not type(env.envs[0].unwrapped).__module__.startswith("ale_py"):
        env.cap_episodes(EVAL_MAX_EPISODE_STEPS)


def eval_cap_note(env: BatchedEnv, env_id: str) -> str | None:
    """The line that says an evaluation episode was cut by the cap on an env without a time
    limit (None while the env has ended every episode itself)."""
    if not isinstance(env, GymBatchEnv) or not env.episodes_cut:
        return None
    return (f"env.id={env_id!r} has no registered time limit (TimeLimit, max_episode_steps): evaluation episodes "
            f"that do not end by themselves are cut at {env.capped_at:,} steps, as {env.episodes_cut:,} were "
            "(env.max_episode_steps caps training and evaluation episodes)")


def _check_observations(obs: Any, live: np.ndarray) -> None:
    """The env's fault, named (as training's FiniteWatch names it), where a copy still running its
    quota of episodes has a NaN or infinite observation: a policy acting on it would give a return
    that means nothing. Integer observations (pixels) cannot hold one."""
    if not isinstance(obs, torch.Tensor) or not obs.is_floating_point():
        return
    bad = to_numpy(~torch.isfinite(obs.reshape(len(obs), -1)).all(dim=1)) & live
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        row = obs[i].reshape(-1)
        value = float(row[~torch.isfinite(row)][0])
        raise NonFiniteError(f"observation was {describe(value)} in an evaluation episode (env copy {i}): "
                             "check the env's observations (reset and step)")


def evaluate(env: BatchedEnv, policy: Callable[[torch.Tensor], torch.Tensor], episodes: int, seed: int | None = None,
             max_steps: int = 1_000_000, episode_returns: list[float] | None = None,
             episode_lengths: list[int] | None = None) -> dict[str, float]:
    """Run `episodes` full episodes and average their return and length (and, as `eval/<key>`,
    each `env.info_keys` value at the episodes' ends).

    Copy i of the batch runs a fixed quota of episodes, so short episodes are not
    over-represented (stopping at the first `episodes` finishers would bias the mean).
    `episode_returns` and `episode_lengths`, if given, get each episode's return and length
    (relayrl.evaluate's std, and its per-episode lists).
    """
    b = env.num_envs
    quota = np.full(b, episodes // b) + (np.arange(b) < episodes % b)
    done_count = np.zeros(b, np.int64)
    ret = np.zeros(b, np.float64)
    length = np.zeros(b, np.int64)
    returns: list[float] = []
    lengths: list[int] = []
    info: dict[str, list[float]] = {}
    try:
        obs = env.reset(seed=seed)
    except Exception as e:
        note_where(e, "in an evaluation episode")
        raise
    for _ in range(max_steps):
        if (done_count >= quota).all():
            break
        _check_observations(obs, done_count < quota)
        with torch.inference_mode():
            try:
                out = env.step(policy(obs))
            except Exception as e:
                note_where(e, "in an evaluation episode")
                raise
        reward = to_numpy(out.reward)
        bad = ~np.isfinite(reward) & (done_count < quota)  # copies past their quota count for nothing
        if bad.any():  # the env's fault: named, not averaged into a NaN return
            first = int(np.flatnonzero(bad)[0])  # (not `i`: the loop below binds NumPy ints to it)
            raise NonFiniteError(f"reward was {describe(float(reward[first]))} in an evaluation episode "
                                 f"(env copy {first}): check the env's reward")
        ret += reward
        length += 1
        done = to_numpy(out.terminated | out.truncated)
        for i in np.flatnonzero(done):
            if done_count[i] < quota[i]:
                returns.append(float(ret[i]))
                lengths.append(int(length[i]))
                for key, values in (out.episode_info or {}).items():
                    info.setdefault(key, []).append(float(values[i]))
            done_count[i] += 1
        ret[done] = 0.0
        length[done] = 0
        obs = out.obs
    if episode_returns is not None:
        episode_returns.extend(returns)
    if episode_lengths is not None:
        episode_lengths.extend(lengths)
    return {
        "average_return": float(np.mean(returns)) if returns else float("nan"),
        "average_episode_length": float(np.mean(lengths)) if lengths else float("nan"),
        "episodes": len(returns),
        **{f"eval/{key}": float(np.mean(values)) for key, values in info.items()},
    }
