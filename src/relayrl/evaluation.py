"""`relayrl.evaluate`: Stable-Baselines3's `evaluate_policy` for a saved policy, a run directory or
any callable, on an env given as an instance, a factory or an id. The episodes themselves run
through `training.evaluate.evaluate`, the function every run's evaluations use."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Literal, NamedTuple, overload

import gymnasium as gym
import numpy as np
import torch

from relayrl.errors import UserError, check_count, one_line
from relayrl.seeding import check_seed
from relayrl.specs import DiscreteSpec, PackedSpec, Spec, describe
from relayrl.training.run_dir import lone_policy_file


class EvalResult(NamedTuple):
    """Mean and standard deviation of the episodes' returns; unpacks as SB3's `(mean, std)`."""

    mean: float
    std: float


@overload
def evaluate(policy: Any, env: Any = ..., episodes: int = ..., deterministic: bool = ..., seed: int | None = ...,
             max_episode_steps: int = ..., return_episode_rewards: Literal[False] = ...) -> EvalResult: ...


@overload
def evaluate(policy: Any, env: Any = ..., episodes: int = ..., deterministic: bool = ..., seed: int | None = ...,
             max_episode_steps: int = ..., *,
             return_episode_rewards: Literal[True]) -> tuple[list[float], list[int]]: ...


@overload
def evaluate(policy: Any, env: Any = ..., episodes: int = ..., deterministic: bool = ..., seed: int | None = ...,
             max_episode_steps: int = ..., *,
             return_episode_rewards: bool) -> EvalResult | tuple[list[float], list[int]]: ...


def evaluate(policy: Any, env: Any = None, episodes: int = 10, deterministic: bool = True,
             seed: int | None = 0, max_episode_steps: int = 0,
             return_episode_rewards: bool = False) -> EvalResult | tuple[list[float], list[int]]:
    """Run `episodes` whole episodes and return the returns' mean and (population) std; with
    `return_episode_rewards` (SB3's name), each episode's return and length as two lists instead.

    `policy`: what `relayrl.load_policy` returns, a run directory (or its policy file), an object
    with SB3's `predict(obs, deterministic=...)`, or any callable taking one observation as the env
    returns it and returning one action. `env`: a Gymnasium env instance (used as it is and left
    open), a callable returning one (called once per env copy), or an env id; None: a run
    directory's own env (its config.toml, as `relayrl eval`), or the env a policy file records
    (its id, kwargs, wrappers and time limit). The env copies (up to 16, one for an
    instance) are reset with seed, seed + 1, ... (None: unseeded), as a run's evaluations are, and a
    loaded policy's samples (`deterministic=False`) are drawn from `seed` too, as are an SB3 model's
    or a function's draws from torch's CPU generator, which is put back after. Episodes are cut
    at `max_episode_steps` where it is > 0 (an instance's own time limit may end them sooner); 0:
    the env's time limit, and an env without one is cut at 1,000 steps (Atari games end their own
    episodes).
    """
    from relayrl.training.evaluate import cap_untimed
    from relayrl.training.evaluate import evaluate as run_episodes

    episodes = check_count("episodes", episodes)
    max_episode_steps = check_count("max_episode_steps", max_episode_steps, zero="for the env's own time limit")
    seed = check_seed(seed)
    source = None if lone_policy_file(policy) else policy  # a run directory: its config.toml says its env
    if isinstance(policy, (str, Path)):  # read once: for its env record and to act
        from relayrl.export import load_policy

        policy = load_policy(policy, deterministic=deterministic, seed=seed)
    batch_env, owned = _batch_env(env, policy, source, episodes, max_episode_steps)
    try:
        act = _policy_fn(policy, deterministic, seed, batch_env.observation_spec, batch_env.action_spec)
        cap_untimed(batch_env, max_episode_steps)  # so that it ends
        returns: list[float] = []
        lengths: list[int] = []
        with _torch_draws_from(seed):
            run_episodes(batch_env, act, episodes, seed=seed, episode_returns=returns, episode_lengths=lengths)
    finally:
        if owned:
            batch_env.close()
    if return_episode_rewards:
        return returns, lengths
    return EvalResult(float(np.mean(returns)), float(np.std(returns)))


@contextlib.contextmanager
def _torch_draws_from(seed: int | None) -> Iterator[None]:
    """torch's CPU generator seeded with `seed` inside and put back after: what an SB3 model's
    `predict(deterministic=False)` (or a function's torch.rand) draws on the CPU repeats with the
    seed and leaves the caller's stream alone, as a loaded policy's own generator does. Unseeded
    (None), the draws go on from the caller's stream."""
    if seed is None:
        yield
        return
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        yield


def _policy_fn(policy: Any, deterministic: bool, seed: int | None, obs_spec: Spec,
               act_spec: Spec) -> Callable[[torch.Tensor], torch.Tensor]:
    """A batched policy (a [B, ...] observation tensor -> [B, ...] actions) from what the user gave."""
    from relayrl.loaded_policy import LoadedPolicy

    if isinstance(policy, LoadedPolicy):
        policy.check_fits(obs_spec, act_spec)
        if not deterministic:  # its samples drawn from `seed`, as a run directory's are: a repeatable evaluation
            policy = policy.reseeded(seed)
        return lambda obs: policy.predict(obs, deterministic=deterministic)[0]
    if hasattr(policy, "predict"):  # an SB3 model, or anything with its spelling
        return _one_at_a_time(lambda o: policy.predict(o, deterministic=deterministic)[0], obs_spec, act_spec)
    if callable(policy):
        return _one_at_a_time(policy, obs_spec, act_spec)
    raise UserError(f"policy={policy!r} is not a policy: give relayrl.load_policy(...)'s result, a run "
                    "directory, or a callable taking an observation and returning an action")


def _one_at_a_time(fn: Callable[[Any], Any], obs_spec: Spec, act_spec: Spec) -> Callable[[torch.Tensor], torch.Tensor]:
    """A user's function sees one NumPy observation at a time, as the env returns them (a Dict
    observation as its dict, not the packed row the batched env carries); what it answers is
    checked against the env's actions, so a wrong one is said in the user's terms."""
    as_env = obs_spec.observation if isinstance(obs_spec, PackedSpec) else (lambda row: row)

    takes = f"this env takes {describe(act_spec)} actions"  # describe gives the env's own shape

    def one(o: np.ndarray) -> np.ndarray:
        answer = fn(as_env(o))
        if isinstance(answer, tuple) and len(answer) == 2 and answer[1] is None:  # SB3's predict(): (action, state)
            raise UserError(f"the policy answered a pair (action, None), as SB3's predict() does; {takes}: answer "
                            "the action (lambda obs: model.predict(obs)[0]), or give the model itself")
        try:
            a = np.asarray(answer)
        except (ValueError, TypeError):  # ragged pieces
            raise UserError(f"the policy answered {one_line(str(answer))}, not an array; {takes}") from None
        fits = a.dtype.kind in "biuf" and a.size == math.prod(act_spec.shape)  # [1] for () and the like: reshaped
        if fits and isinstance(act_spec, DiscreteSpec):  # an index, 1.0 included
            index = float(a.reshape(()))
            fits = index.is_integer() and 0 <= index < act_spec.n
        if not fits:
            raise UserError(f"the policy answered {one_line(str(a.tolist()))} ({a.dtype}, shape {a.shape}) to one "
                            f"observation; {takes}")
        return (a.astype(np.int64) if isinstance(act_spec, DiscreteSpec) else a).reshape(act_spec.shape)

    scalar = isinstance(obs_spec, DiscreteSpec)  # the env gives a number; a Box of shape () a 0-d array

    def act(obs: torch.Tensor) -> torch.Tensor:
        batch = obs.cpu().numpy()
        return torch.as_tensor(np.stack([one(batch[i] if scalar else batch[i, ...]) for i in range(len(batch))]))

    return act


def _batch_env(env: Any, policy: Any, run_dir: Any, episodes: int, max_episode_steps: int) -> tuple[Any, bool]:
    """The batched env to run on, and whether it is ours to close; `run_dir`: where `policy`
    was loaded from a run directory, that directory (else None)."""
    from relayrl.envs.gym import GymBatchEnv
    from relayrl.training.evaluate import make_eval_env

    if isinstance(env, gym.Env):
        # One copy: the user's own instance, its episodes one after another.
        batch = GymBatchEnv([lambda: env])
        if max_episode_steps > 0:  # as an id's or a factory's copies take it for their time limit (else ignored)
            batch.cap_episodes(max_episode_steps)
        return batch, False
    if env is None:
        from relayrl.loaded_policy import LoadedPolicy

        if not isinstance(policy, LoadedPolicy):
            raise UserError("env=None evaluates on the env a run directory or a policy file records; with this "
                            "policy give env (a Gymnasium env, a callable returning one, or an env id)")
        return recorded_env(run_dir if run_dir is not None else policy, episodes, max_episode_steps)[0], True
    if isinstance(env, str):
        from relayrl.console import say

        # a run directory's config.toml imports its wrappers anyway: they are the policy's input
        return named_env(env, policy, episodes, max_episode_steps, say=say, run_code=run_dir is not None), True
    if isinstance(env, gym.vector.VectorEnv) or hasattr(env, "step_async"):  # Gymnasium's or SB3's VecEnv
        raise UserError(f"env={type(env).__name__} is a vector env; give one env, an env id, or a callable "
                        "returning one env: relayrl.evaluate runs its own copies of it (up to 16)")
    if callable(env):
        from relayrl.dispatch import factory_env_id

        return make_eval_env(factory_env_id(env), episodes, max_episode_steps, factory=env), True
    raise UserError(f"env={env!r} is not an env: give a Gymnasium env, a callable returning one, or an env id")


def named_env(env_id: str, policy: Any, episodes: int, max_episode_steps: int = 0,
              say: Callable[[str], None] | None = None, run_code: bool = False) -> Any:
    """The eval env for an env id the user names. Where it is the id a loaded policy records,
    the env.kwargs and time limit it was trained with apply. Its env.wrappers (the policy's
    input, over any env id) apply with `run_code` only: a run directory's, whose config.toml
    imports them for `relayrl eval` anyway, or a policy file trusted (--trust-code); a policy
    file on its own runs no code. `say` gets a line saying what applies."""
    from relayrl.loaded_policy import LoadedPolicy
    from relayrl.training.evaluate import make_eval_env

    if not isinstance(policy, LoadedPolicy):
        return make_eval_env(env_id, episodes, max_episode_steps)
    same = policy.env_id == env_id
    wrappers = list(policy.env_wrappers) if run_code else []
    # the caller's max_episode_steps, where given, is the time limit instead of the recorded one
    kept = [f"env.kwargs {policy.env_kwargs}"] * bool(same and policy.env_kwargs) + [
        f"env.max_episode_steps={policy.max_episode_steps}"] * bool(same and policy.max_episode_steps and
                                                                   not max_episode_steps) + [
        f"env.wrappers {wrappers}"] * bool(wrappers)
    applied = f"{' and '.join(kept)} appl{'y' if len(kept) > 1 else 'ies'}" if kept else ""
    dropped = f"its env.wrappers {policy.env_wrappers} do not apply (a policy file runs no code; from its run " \
        "directory, or with --trust-code, they do)" if policy.env_wrappers and not run_code else ""
    if say is not None and (applied or dropped):
        whose = f"{env_id} is the env the policy was trained on" if same else \
            f"the policy was trained on {policy.env_id}, evaluated here on {env_id}"
        say(f"{whose}: {'; '.join(p for p in (applied, dropped) if p)}")
    steps = max_episode_steps or (policy.max_episode_steps if same else 0)
    return make_eval_env(env_id, episodes, steps, kwargs=policy.env_kwargs if same else None, wrappers=wrappers)


def recorded_env(source: Any, episodes: int, max_episode_steps: int = 0, info_keys: bool = False,
                 policy: Any = None) -> tuple[Any, str]:
    """The eval env (`make_eval_env`) and its id, of the env a run directory's config.toml records
    (`source` a run directory or a file in it), or else a policy file's own record (`source` a
    lone policy file, loaded again unless `policy` is that file's, or a loaded policy): a
    registered id, its kwargs and time limit (`max_episode_steps` overrides the time limit where
    it is not 0); with `info_keys`, a run's env.info_keys too. A file naming code to import
    (`module:Name`, wrappers) is refused: a policy file runs no code."""
    from relayrl.envs.resolve import names_module
    from relayrl.export import load_policy
    from relayrl.loaded_policy import LoadedPolicy
    from relayrl.presets import load_config
    from relayrl.training.evaluate import make_eval_env
    from relayrl.training.run_dir import RunDir

    if isinstance(source, (str, Path)):
        if not lone_policy_file(source):
            rd = RunDir.of(source)
            rd.require()
            config = load_config(str(rd.config))
            c = config.env
            return make_eval_env(c.id, episodes, max_episode_steps or c.max_episode_steps,
                                 kwargs=config.eval_env_kwargs(), wrappers=c.wrappers,
                                 info_keys=c.info_keys if info_keys else (), vectorization=c.vectorization,
                                 num_workers=c.num_workers), c.id
        source = policy if policy is not None else load_policy(source)  # a policy file on its own
    assert isinstance(source, LoadedPolicy)
    give = "give the env to evaluate on (--env ENV_ID; in Python, env=)"
    if not source.env_id:
        raise UserError(f"the policy file records no env id: {give}")
    if names_module(source.env_id) or source.env_wrappers:  # a shared file runs no code: it names an env only
        code = ", ".join([source.env_id] * names_module(source.env_id) + source.env_wrappers)
        raise UserError(f"the policy file's env would import and run code it names ({code}), which a policy file "
                        f"is not trusted to: {give}")
    return make_eval_env(source.env_id, episodes, max_episode_steps or source.max_episode_steps,
                         kwargs=source.env_kwargs), source.env_id
