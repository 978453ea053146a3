"""`make_env`: a batched env from an id, with the copies stepped here, in worker processes, or
as one stateless torch batch. It sits above gym.py and vector.py, which know nothing of it."""

from __future__ import annotations

import contextlib
import os
import random
import re
import warnings
from collections.abc import Iterator
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from relayrl.envs.ale_vector import make_ale_env
from relayrl.envs.gym import BatchEnvBase, GymBatchEnv
from relayrl.envs.probe import first_problem
from relayrl.envs.resolve import EnvFn, apply_wrappers, names_module, resolve_env_fn
from relayrl.envs.stateless.adapter import STATELESS_ENVS, StatelessBatchEnv, make_batch_env
from relayrl.envs.vector import AsyncGymBatchEnv
from relayrl.errors import UserError, install, note_where
from relayrl.user_code import load_callable


def make_env(env_id: str, num_envs: int = 1, max_episode_steps: int = 0, render_mode: str | None = None,
             time_limit_terminates: bool = False, vectorization: str = "sync",
             device: str | torch.device = "cpu", info_keys: tuple[str, ...] | list[str] = (),
             num_workers: int = 0, kwargs: dict[str, Any] | None = None,
             wrappers: tuple[str, ...] | list[str] = (), factory: EnvFn | None = None
             ) -> BatchEnvBase | StatelessBatchEnv:
    """A batched env of `num_envs` copies of `env_id`: stepped in this process ("sync") or
    shared out over `num_workers` worker processes ("async", 0: one per core; see envs/vector.py),
    or, for `relayrl/Atari-<Game>-v0`, by ale-py's vector env on `num_workers` threads ("ale";
    see envs/ale_vector.py).
    A stateless torch env id (`relayrl/StatelessPendulum-v0`) gives all copies as one batch of
    tensors on `device`.
    `info_keys`: info values to report at each episode's end (`StepOutput.episode_info`).
    `kwargs`, `wrappers`, `factory`: see `resolve_env_fn` (env.kwargs, env.wrappers, and the
    env factory given to `relayrl.train`)."""
    if env_id in STATELESS_ENVS and render_mode is None and factory is None:
        if info_keys or kwargs or wrappers:
            what = "env.info_keys" if info_keys else "env.kwargs (eval.env_kwargs)" if kwargs else "env.wrappers"
            raise UserError(f"{what} is not supported by stateless envs ({env_id!r} is a batch of tensors)")
        return make_batch_env(env_id, num_envs, device, max_episode_steps=max_episode_steps,
                              time_limit_terminates=time_limit_terminates)
    if vectorization == "ale":
        if render_mode is not None or wrappers or factory is not None:
            what = "render_mode" if render_mode is not None else "env.wrappers" if wrappers else "an env factory"
            raise UserError(f"{what} is not supported with env.vectorization='ale' (ale-py steps the copies "
                            "in C++); use env.vectorization='sync'")
        ale = make_ale_env(env_id, num_envs, max_episode_steps, time_limit_terminates, device, num_workers, kwargs)
        ale.info_keys = tuple(info_keys)
        return ale
    fn = resolve_env_fn(env_id, max_episode_steps, render_mode, kwargs, wrappers, factory)
    env: BatchEnvBase
    with making(env_id, users_code=bool(wrappers) or factory is not None):
        if vectorization == "async" and num_envs > 1:
            env = AsyncGymBatchEnv([fn] * num_envs, time_limit_terminates, num_workers)
        else:
            env = GymBatchEnv([fn] * num_envs, time_limit_terminates)
    env.info_keys = tuple(info_keys)
    return env


@contextlib.contextmanager
def making(env_id: str, users_code: bool = False) -> Iterator[None]:
    """Gymnasium's own errors while the copies are made (a missing dependency, a bad kwarg) as one
    line; a registered env's import, OS and attribute errors too, unless the user's code takes part
    (`users_code`: their wrappers or factory; a `module:Name` id), whose traceback they need."""
    try:
        yield
    except gym.error.Error as e:
        if extra := missing_extra(e):  # Gymnasium's line names its own install (swig, "gymnasium[box2d]")
            raise UserError(f"env.id={env_id!r} needs Gymnasium's {extra} dependencies: {install(extra)}") from None
        raise UserError(f"env.id={env_id!r} could not be made: {e}{gl_hint(e)}{newer_hint(env_id, e)}") from None
    except (ImportError, OSError, AttributeError) as e:  # a registered env's moved ids, a missing GL library
        if users_code or names_module(env_id):
            raise
        said = " ".join(str(e).split()).rstrip(".")  # the line goes on after it
        raise UserError(f"env.id={env_id!r} could not be made: {type(e).__name__}: {said}{gl_hint(e)}"
                        f"{newer_hint(env_id, e)}") from None


def newer_hint(env_id: str, error: Exception) -> str:
    """Where a registered id fails and the registry holds a newer version of the same env
    (HalfCheetah-v3, whose MuJoCo bindings moved out of Gymnasium): that version's id, unless
    Gymnasium's own line already names it (a deprecated version's "Please use ... instead")."""
    try:
        namespace, name, version = gym.envs.registration.parse_env_id(env_id)
    except gym.error.Error:
        return ""
    versions = [s.version for s in gym.envs.registry.values()
                if s.namespace == namespace and s.name == name and s.version is not None]
    if version is None or not versions or max(versions) <= version:
        return ""
    newest = gym.envs.registration.get_env_id(namespace, name, max(versions))
    return "" if newest in str(error) else f"; {newest} is this env's newest version"


def missing_extra(error: Exception) -> str | None:
    """The relayrl extra (box2d, mujoco) that brings a Gymnasium env's missing dependency."""
    if isinstance(error, gym.error.DependencyNotInstalled):
        for extra in ("box2d", "mujoco"):  # Gymnasium's own message names its extra: pip install "gymnasium[...]"
            if f"gymnasium[{extra}]" in str(error):
                return extra
    return None


_GL = re.compile(r"OpenGL|\bgl[A-Z]|EGL|OSMesa|GLFW|MUJOCO_GL")


def gl_hint(error: Exception) -> str:
    """Where `error` is a missing OpenGL library (MuJoCo making or rendering an env without a
    display): the setting that picks another."""
    if not _GL.search(f"{type(error).__name__} {error}"):
        return ""
    chosen = f" (MUJOCO_GL={os.environ['MUJOCO_GL']!r} now)" if "MUJOCO_GL" in os.environ else ""
    return (f"; MuJoCo renders without a display through MUJOCO_GL=egl (a GPU driver) or MUJOCO_GL=osmesa "
            f"(libOSMesa){chosen}")


def is_user_env(env_id: str, factory: EnvFn | None = None) -> bool:
    """A user's own env (`module:Class`, `module:EnvId-v0`, a factory), not a known id: the
    envs that are checked at the start of a run and whose missing time limit is worth a line."""
    return factory is not None or names_module(env_id)


# Gymnasium's wrappers that change rewards without being a RewardWrapper.
REWARD_CHANGING = ("NormalizeReward",)
# Gymnasium's wrappers whose running statistics live in each env copy, not in the policy.
OWN_STATISTICS = ("NormalizeObservation",)


def wrapper_layers(env_id: str, kwargs: dict[str, Any] | None = None, wrappers: tuple[str, ...] | list[str] = (),
                   factory: EnvFn | None = None, max_episode_steps: int = 0) -> list[type]:
    """The classes of the layers `wrappers` put over one fresh copy of the env, innermost first;
    [] where the env cannot be made here (the run says why when it makes its own). The global
    RNGs are left as they were."""
    if not wrappers:
        return []
    found: list[type] = []
    with global_rngs_kept():
        try:
            base = resolve_env_fn(env_id, max_episode_steps, None, kwargs, (), factory)()
            env = apply_wrappers(base, [load_callable(w, "env.wrappers") for w in wrappers])
            layer = env
            while layer is not base and isinstance(layer, gym.Wrapper):
                found.append(type(layer))
                layer = layer.env
            env.close()
        except Exception:  # the run makes its envs next and reports what is wrong there
            return []
    return found[::-1]


def reward_wrappers(layers: list[type]) -> list[str]:
    """The reward-changing ones of `wrapper_layers` (a `gym.RewardWrapper`, NormalizeReward), by
    class name: evaluations report returns of those rewards."""
    return [t.__name__ for t in layers if issubclass(t, gym.RewardWrapper) or t.__name__ in REWARD_CHANGING]


def statistics_wrappers(layers: list[type]) -> list[str]:
    """The ones of `wrapper_layers` that keep running statistics in each env copy (OWN_STATISTICS)."""
    return [t.__name__ for t in layers if t.__name__ in OWN_STATISTICS]


@contextlib.contextmanager
def global_rngs_kept() -> Iterator[None]:
    """torch's, NumPy's and Python's global generators as they were before: an env made only to
    look at it leaves a run as it would have been without the look, and a run leaves its caller's
    (`training.process.caller_state_kept`)."""
    rng = (torch.get_rng_state(), np.random.get_state(), random.getstate())
    try:
        yield
    finally:
        torch.set_rng_state(rng[0])
        np.random.set_state(rng[1])
        random.setstate(rng[2])


def check_env(env_id: str, kwargs: dict[str, Any] | None = None, wrappers: tuple[str, ...] | list[str] = (),
              factory: EnvFn | None = None, max_episode_steps: int = 0) -> list[str]:
    """Gymnasium's env checker on one fresh copy: its complaints as lines (warnings, not
    failures), after a UserError for what will break the run (`probe.first_problem`). The
    global RNGs are left as they were, so a checked run is the unchecked one."""
    from gymnasium.utils.env_checker import check_env as gym_check_env

    lines: list[str] = []
    with global_rngs_kept():
        env = resolve_env_fn(env_id, max_episode_steps, None, kwargs, wrappers, factory)()
        try:
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # the checker below reports what it finds once
                    problem = first_problem(env)
                obs, info = env.reset(seed=0) if problem is None else (None, {})  # (a Gymnasium reset, found)
            except Exception as e:  # the env's own: its traceback, and where relayrl called it
                note_where(e, "by the env in relayrl's check before training (reset() of one fresh copy, then a step "
                              "of a random action)")
                raise
            if problem is not None:
                who = "the env from the factory given to relayrl.train" if factory is not None else f"env.id={env_id!r}"
                raise UserError(f"{who}: {problem}")
            checked, cast = _cast_observations(env, obs)
            lines += [line for line in (cast, _action_masks_line(env, info)) if line is not None]
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                try:
                    gym_check_env(_PlainFlags(checked), skip_render_check=True, skip_close_check=True)
                except Exception as e:  # the checker's assertions: reported, the run goes on
                    lines.append(f"{type(e).__name__}: {e}")
            for w in caught:
                text = str(w.message)
                if not any(quiet in text for quiet in _NOT_FINDINGS):
                    lines.append(text)
        finally:
            env.close()
    clean = list(dict.fromkeys(" ".join(_ANSI.sub("", line).removeprefix("WARN: ").split()) for line in lines))
    if any(sign in line for line in clean for sign in _UNSEEDED):  # what Gymnasium's findings mean for a run
        clean.append("runs of this env with the same seed will not repeat: call super().reset(seed=seed) in its "
                     "reset and draw every random number from self.np_random (README: Seeding and reproducibility)")
    return clean


class _PlainFlags(gym.Wrapper):
    """Terminated / truncated flags of NumPy's bool as Python's: Gymnasium's checker asserts
    `truncated is False` after one step, which np.False_ (a valid flag, what a comparison of
    arrays gives) fails with "something has gone very wrong", and its later checks never run."""

    def step(self, action: Any) -> tuple[Any, Any, Any, Any, Any]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        plain = [bool(f) if isinstance(f, np.bool_) else f for f in (terminated, truncated)]
        return obs, reward, plain[0], plain[1], info


def _action_masks_line(env: gym.Env, info: dict[str, Any]) -> str | None:
    """A line where the env offers invalid-action masks (sb3-contrib's MaskablePPO reads
    `action_masks()` or `info["action_mask"]`, `info` being a reset's): no relayrl algorithm reads
    them, so its policies pick masked actions too, which a run would otherwise leave unsaid."""
    if not callable(getattr(env.unwrapped, "action_masks", None)) and not (isinstance(info, dict)
                                                                         and "action_mask" in info):
        return None
    return ("the env gives action masks (action_masks() or info['action_mask']): relayrl does not read them, so "
            "its policies also pick the actions they mask out; the env must handle those (a penalty, or "
            "mapping them to a valid action)")


def _cast_observations(env: gym.Env, obs: Any) -> tuple[gym.Env, str | None]:
    """`env` with its observations cast to its Boxes' dtypes, and a line saying so, where it
    returns arrays of another number dtype (float64, int64; `obs` is a reset's), as the whole
    observation or as Dict / Tuple entries: relayrl casts them, and Gymnasium's checker would
    stop at its first assertion ("not within the observation space", of values inside the
    bounds), before its seed and determinism checks ever ran."""
    space = env.observation_space
    found: list[tuple[str, np.dtype, gym.spaces.Box]] = []
    _cast(space, obs, found)
    if not found:
        return env, None
    if isinstance(space, gym.spaces.Box):
        line = (f"observations come as {found[0][1]} where observation_space is {space}: relayrl casts them to "
                f"{space.dtype} (return {space.dtype} arrays, or declare the space's dtype, to silence this line)")
    else:
        entries = ", ".join(f"{where} as {dtype} where its space is {box}" for where, dtype, box in found)
        line = (f"observation entries come in other dtypes than their spaces': {entries}; relayrl casts them (return "
                "arrays of the spaces' dtypes, or declare those dtypes, to silence this line)")
    return gym.wrappers.TransformObservation(env, lambda o: _cast(space, o), space), line


def _cast(space: gym.Space, obs: Any, found: list[tuple[str, np.dtype, gym.spaces.Box]] | None = None,
          where: str = "") -> Any:
    """`obs` with each Box's array of numbers in the Box's dtype (Dict and Tuple entries too).
    Each entry whose dtype Box.contains refuses (float64 for float32, float for int) goes into
    `found` as (entry, dtype, Box); a list, or a dtype that casts safely (int32 for int64), is
    no finding: Box.contains takes them."""
    if isinstance(space, gym.spaces.Dict) and isinstance(obs, dict):
        return {k: _cast(space.spaces[k], v, found, f"{where}[{k!r}]") if k in space.spaces else v
                for k, v in obs.items()}
    if isinstance(space, gym.spaces.Tuple) and isinstance(obs, tuple | list) and len(obs) == len(space.spaces):
        pairs = enumerate(zip(space.spaces, obs, strict=True))
        return tuple(_cast(s, o, found, f"{where}[{i}]") for i, (s, o) in pairs)
    if isinstance(space, gym.spaces.Box) and isinstance(obs, np.ndarray | np.generic) and obs.dtype.kind in "biuf":
        if found is not None and not np.can_cast(obs.dtype, space.dtype):
            found.append((where, obs.dtype, space))
        return np.asarray(obs, space.dtype)
    return obs


# Gymnasium's checker's findings of an env that does not seed itself from reset(seed=...)
_UNSEEDED = ("does not call `super().reset(seed=seed)`", "random number generator to have been generated given a seed",
             "is non-deterministic", "Deterministic step observations are not equivalent")
_ANSI = re.compile(r"\x1b\[[0-9;]*m")  # gymnasium's logger colours its warnings
# What Gymnasium's checker says that is no finding here: wrappers (a TimeLimit, env.wrappers) are
# ours to add, and a Box without bounds (CartPole's, most MuJoCo envs') is one relayrl takes.
_NOT_FINDINGS = ("is different from the unwrapped version", "minimum value is -infinity",
                 "maximum value is infinity")
