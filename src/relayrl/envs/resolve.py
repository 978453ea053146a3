"""How an env.id becomes a factory of one env: a Gymnasium id (`CartPole-v1`), a user's
`package.module:Class` (or a callable there), Gymnasium's `package.module:EnvId-v0`, or a
factory given in Python; with env.kwargs, the time limit and env.wrappers over it."""

from __future__ import annotations

import dataclasses
import difflib
import importlib
import inspect
import os
import re
import sys
from collections.abc import Callable
from typing import Any

import cloudpickle
import gymnasium as gym

from relayrl.envs.atari import missing_ale_hint, register_on_demand
from relayrl.errors import UserError
from relayrl.user_code import bind_error, import_user_module, load_callable, near_callable

EnvFn = Callable[[], gym.Env]
TYPO = 0.85  # difflib's ratio above which an unregistered id is read as a typo of a registered one


def no_display() -> bool:
    """Linux without an X11 or Wayland display (a server, a container, an SSH session without -X)."""
    return sys.platform.startswith("linux") and not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY")


def names_module(env_id: str) -> bool:
    """`package.module:Name` (a user's class, callable or `EnvId-v0`), not a Gymnasium id such as
    `relayrl/Atari-Pong-v0` or `ALE/Pong-v5`."""
    return ":" in env_id and "/" not in env_id.split(":", 1)[0]


def names_python_factory(env_id: str) -> bool:
    """An env.id recorded for an env factory given to relayrl.train in Python that no import
    finds (a lambda, a local function, one in `__main__`): only the same `env=` makes it again."""
    if not names_module(env_id):
        return False
    module_name, name = env_id.split(":", 1)
    return "<" in name or module_name == "__main__"


def resolve_env_fn(env_id: str, max_episode_steps: int = 0, render_mode: str | None = None,
                   kwargs: dict[str, Any] | None = None, wrappers: list[str] | tuple[str, ...] = (),
                   factory: EnvFn | None = None) -> EnvFn:
    """A factory for one env: a Gymnasium id (`CartPole-v1`), `package.module:Class` (or any
    callable there returning an env), Gymnasium's `package.module:EnvId-v0` (importing the module
    registers the id), or `factory` itself (a callable given in Python; `env_id` then only names it).
    `kwargs` go to the class or `gymnasium.make`; `wrappers` (`module:Callable`, each taking
    and returning an env) are applied in order over the made env and its time limit."""
    kwargs = dict(kwargs or {})
    if kwargs.get("render_mode") == "human" and no_display():  # GLFW and SDL abort the process, past any except
        raise UserError("env.kwargs render_mode='human' opens a window, and this machine has no display (DISPLAY "
                        "is unset): leave render_mode out (relayrl video records episodes without a display)")
    if render_mode is not None:
        kwargs["render_mode"] = render_mode
    wrap = [load_callable(w, "env.wrappers") for w in wrappers]
    if factory is not None:
        base = _custom_fn(env_id, factory, kwargs, max_episode_steps)
    elif names_module(env_id):
        module_name, name = env_id.split(":", 1)
        if module_name == "__main__" and hasattr(sys.modules.get("__main__"), name):  # set by hand in a notebook
            raise UserError(f"env.id={env_id!r} names {name} of the script or notebook itself, which no other "
                            f"process imports: give it as env={name} (relayrl.train, relayrl.evaluate), or put it "
                            f"in a module beside the script and name it 'mymodule:{name}'")
        if names_python_factory(env_id):
            raise UserError(f"env.id={env_id!r} records an env factory given to relayrl.train in Python that "
                            "cannot be imported here (a lambda, a functools.partial, a local function or __main__); "
                            "pass the same env= again in Python (relayrl eval: --env ENV_ID, a registered id or "
                            "package.module:Class that makes the same env), or make it a function in a module "
                            "and name it in env.id")
        module = import_user_module(module_name, f"env.id={env_id!r}")
        if hasattr(module, name):
            target = getattr(module, name)
            if isinstance(target, type) and not issubclass(target, gym.Env) or not callable(target):
                raise UserError(f"env.id={env_id!r} is not a gymnasium.Env subclass (nor a callable returning one)")
            base = _custom_fn(env_id, target, kwargs, max_episode_steps)
        elif name in gym.registry:  # Gymnasium's own `module:EnvId-v0`: the import registered it
            base = _registered_fn(name, kwargs, max_episode_steps, module_name)
        else:
            hint = near_callable(module, module_name, name)
            raise UserError(f"env.id={env_id!r}: module {module_name!r} has no {name!r} and registers no "
                            f"Gymnasium id {name!r}{hint} (valid: package.module:Class or package.module:EnvId-v0)")
    else:
        register_on_demand(env_id)
        if env_id not in gym.registry:
            close = difflib.get_close_matches(env_id, list(gym.registry), n=3)
            module_name, _, name = env_id.rpartition(".")
            if not close and module_name and name.isidentifier():  # `mymod.MyEnv`: Python's dot for the colon
                close = [f"{module_name}:{name}"]
            ale = missing_ale_hint(env_id)
            near = f"did you mean {', '.join(close)}?" if close else ""
            if ale and near and difflib.SequenceMatcher(None, env_id, close[0]).ratio() < TYPO:
                hint = f"{ale}; otherwise {near}"  # Pong-v4's nearest id is Ant-v4: the extra first
            else:  # a typo of a registered id (MyCoridor-v0) first; ale-py's ids look like any CamelCase-v0
                hint = (f"; {near}" if near else "") + ale
            raise UserError(
                f"env.id={env_id!r} is not a registered Gymnasium id{hint} "
                "(valid: a Gymnasium id such as CartPole-v1, relayrl/..., package.module:Class, or "
                "package.module:EnvId-v0 for an id that module registers with gymnasium.register)"
            )
        base = _registered_fn(env_id, kwargs, max_episode_steps)
    return (lambda: apply_wrappers(base(), wrap)) if wrap else base


def _custom_fn(env_id: str, make: Callable[..., Any], kwargs: dict[str, Any], max_episode_steps: int) -> EnvFn:
    """A user's class or factory; no OrderEnforcing (see `_registered_fn`)."""

    def make_custom() -> gym.Env:
        # Arguments that do not fit its signature are one line; a TypeError from inside its own
        # code is its bug, with its traceback.
        if (why := bind_error(make, **kwargs)) is not None:
            video = ("; relayrl video makes the env with render_mode='rgb_array': give the class a render_mode "
                     "argument" if "render_mode" in why else "")
            raise UserError(_arguments_line(env_id, make, why, kwargs, {}) + video)  # no preset's kwargs to blame
        env = make(**kwargs)
        if not isinstance(env, gym.Env):
            raise UserError(f"env.id={env_id!r} returned {type(env).__name__}, not a gymnasium.Env")
        if max_episode_steps > 0:
            env = gym.wrappers.TimeLimit(env, max_episode_steps)
        return env

    return make_custom


def _registered_fn(env_id: str, kwargs: dict[str, Any], max_episode_steps: int, module: str = "") -> EnvFn:
    given = dict(kwargs)  # the user's env.kwargs, without the time limit added below
    if max_episode_steps > 0:
        kwargs = {**kwargs, "max_episode_steps": max_episode_steps}
    # An id the user's script or notebook registered (`gymnasium.register`) is in this process's
    # registry only: a worker process started by spawn (macOS, Windows) has a fresh one.
    known = gym.registry.get(env_id)
    if known is not None:
        try:  # the spec travels with the factory to worker processes: one holding what cannot stays home
            cloudpickle.dumps(known)
        except Exception:
            known = None

    def make_registered() -> gym.Env:
        # Again in a worker process that starts with a fresh registry.
        if module:
            importlib.import_module(module)
        register_on_demand(env_id)
        if env_id not in gym.registry and known is not None:
            gym.registry[env_id] = known
        # disable_env_checker: the passive checker costs a measurable share of a tiny env's step
        # and only warns. No OrderEnforcing either (as for a user's class above): it only raises
        # on a step or render before the first reset, which the batched envs never do, and it
        # costs a share of every step (docs/benchmarks.md).
        spec = dataclasses.replace(gym.spec(env_id), order_enforce=False)
        try:
            return gym.make(spec, disable_env_checker=True, **kwargs)
        except (TypeError, KeyError, ValueError, ArithmeticError, AssertionError, IndexError) as e:
            if isinstance(e, TypeError) and "argument" in str(e):
                raise UserError(_arguments_line(env_id, spec.entry_point, str(e), kwargs, given)) from None
            # a registered env that fails on a value it was given (FrozenLake's map_name="8X8": a
            # KeyError of its map table; Hopper's frame_skip=0: a ZeroDivisionError) has a typo in
            # env.kwargs, not a bug; without env.kwargs, or from a user's module, it is their
            # code's traceback that helps
            if not given or module:
                raise
            raise UserError(f"env.id={env_id!r} does not take the values given ({type(e).__name__}: {e}); "
                            f"arguments passed (env.kwargs, and eval.env_kwargs to evaluation envs): {given}"
                            ) from None

    return make_registered


def _arguments_line(env_id: str, entry_point: Any, error: str, kwargs: dict[str, Any], given: dict[str, Any]) -> str:
    """An env's refusal of an argument (`error`, the TypeError's words): which one, the near miss
    among the env class's own arguments, or, for an argument none is near, that env.kwargs a
    preset set stay when --set env.id changes the env (ppo-lunarlander-continuous's
    continuous=true on Hopper-v5)."""
    named = re.search(r"unexpected keyword argument '(\w+)'", error)
    if named is None:
        return (f"env.id={env_id!r} does not take the arguments given ({error}); arguments passed (env.kwargs, and "
                f"eval.env_kwargs to evaluation envs): {sorted(kwargs) or 'none'}")
    own = _own_arguments(entry_point)
    close = difflib.get_close_matches(named[1], own, n=1, cutoff=0.6)
    line = f"env.id={env_id!r} takes no argument {named[1]!r} (env.kwargs, or eval.env_kwargs for evaluation)"
    line += f"; did you mean {close[0]!r}?" if close else ""
    line += f" (its own arguments: {', '.join(own)})" if own else ""
    if not close and named[1] in given:
        line += "; env.kwargs a preset sets stay when --set env.id changes the env: --set 'env.kwargs={}' clears them"
    return line


def _own_arguments(entry_point: Any) -> list[str]:
    """The keyword arguments an env class (or factory) names itself: those a **kwargs passes on
    to a base class (MuJoCo's render settings) are not among them."""
    try:
        target = gym.envs.registration.load_env_creator(entry_point) if isinstance(entry_point, str) else entry_point
        params = inspect.signature(target).parameters.values()
    except (ImportError, AttributeError, ValueError, TypeError):
        return []
    kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    return [p.name for p in params if p.kind in kinds and p.name != "self"]


def apply_wrappers(env: gym.Env, wrappers: list[Callable[[gym.Env], gym.Env]]) -> gym.Env:
    """`env` in each of `wrappers` (env.wrappers' callables), in order."""
    for w in wrappers:
        _check_takes_an_env(w, env)
        try:
            env = w(env)
        except UserError:
            raise
        except Exception as e:  # the wrapper's own traceback, said to be from env.wrappers
            e.add_note(f"relayrl: raised by env.wrappers' {_wrapper_name(w)} over {env}")
            raise
        if not isinstance(env, gym.Env):
            raise UserError(f"env.wrappers: {w!r} returned {type(env).__name__}, not a gymnasium.Env")
    return env


def _wrapper_name(wrapper: Callable[..., Any]) -> str:
    return f"{getattr(wrapper, '__module__', '?')}:{getattr(wrapper, '__qualname__', repr(wrapper))}"


def _check_takes_an_env(wrapper: Callable[..., Any], env: gym.Env) -> None:
    """One line for a wrapper that needs more than the env (its own errors stay its own)."""
    if (why := bind_error(wrapper, env)) is not None:
        raise UserError(f"env.wrappers: {_wrapper_name(wrapper)} cannot be called with the env alone ({why}); give "
                        "a function of the env that passes the rest, e.g. def wrap(env): return TimeLimit(env, 500)")
