"""Tiny envs with known episode structure, importable as `toy_envs:Class` in tests."""

from __future__ import annotations

import multiprocessing
import os
import time

import gymnasium as gym
import numpy as np
from gymnasium.envs.classic_control import CartPoleEnv
from gymnasium.utils import EzPickle


class Countdown(gym.Env):
    """obs = [steps taken, episode index]; reward 1 per step; terminates after `length` steps.

    With `truncate_at` < length the episode is cut by a time limit (truncated) instead.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, length: int = 3, truncate_at: int = 0, render_mode: str | None = None) -> None:
        self.length = length
        self.truncate_at = truncate_at
        self.render_mode = render_mode
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (2,), np.float32)
        self.action_space = gym.spaces.Discrete(2)
        self.t = 0
        self.episode = -1

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.t = 0
        self.episode += 1
        return np.array([self.t, self.episode], np.float32), {}

    def step(self, action):
        self.t += 1
        obs = np.array([self.t, self.episode], np.float32)
        terminated = self.t >= self.length
        truncated = bool(self.truncate_at) and self.t >= self.truncate_at and not terminated
        return obs, 1.0, terminated, truncated, {}

    def render(self):
        return np.full((16, 16, 3), 40 * self.t % 255, np.uint8)


class Resized(Countdown):
    """Countdown whose observation has `size` entries (the steps taken, repeated)."""

    def __init__(self, size: int = 2) -> None:
        super().__init__()
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (size,), np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = super().reset(seed=seed)
        return np.full(self.observation_space.shape, obs[0], np.float32), info

    def step(self, action):
        obs, *rest = super().step(action)
        return np.full(self.observation_space.shape, obs[0], np.float32), *rest


class Travel(Countdown):
    """Countdown whose info has `x` = 10 * episode index + steps taken (so each episode ends at
    x = 10 * episode + length) and a non-numeric `name`. The episode index counts per copy."""

    def step(self, action):
        obs, reward, terminated, truncated, _ = super().step(action)
        return obs, reward, terminated, truncated, {"x": 10 * self.episode + self.t, "name": "travel"}


class Truncating(Countdown):
    """Episodes of 2 steps cut by a time limit, never terminated."""

    def __init__(self, render_mode: str | None = None) -> None:
        super().__init__(length=100, truncate_at=2, render_mode=render_mode)


class BetterAction(gym.Env):
    """One-step bandit with a 4-dim observation: action 1 pays 1, action 0 pays 0.

    Any working DQN learns it in a few hundred steps; a broken one does not.
    """

    def __init__(self, render_mode: str | None = None) -> None:
        self.observation_space = gym.spaces.Box(-1, 1, (4,), np.float32)
        self.action_space = gym.spaces.Discrete(2)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        return self.np_random.uniform(-1, 1, 4).astype(np.float32), {}

    def step(self, action):
        return self.np_random.uniform(-1, 1, 4).astype(np.float32), float(action == 1), True, False, {}


class NotAnEnv:
    pass


class Reach(gym.Env):
    """One-step continuous task: obs t ~ U(-1, 1)^2, action a in [-2, 2]^2, reward -|a - 1.5 t|^2.

    The best action is 1.5 t (return 0); a uniform random policy averages about -2.8. Bounds
    other than [-1, 1] check that SAC rescales its tanh output.
    """

    def __init__(self, render_mode: str | None = None) -> None:
        self.observation_space = gym.spaces.Box(-1, 1, (2,), np.float32)
        self.action_space = gym.spaces.Box(-2, 2, (2,), np.float32)
        self._t = np.zeros(2, np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._t = self.np_random.uniform(-1, 1, 2).astype(np.float32)
        return self._t, {}

    def step(self, action):
        reward = -float(np.sum((np.asarray(action) - 1.5 * self._t) ** 2))
        self._t = self.np_random.uniform(-1, 1, 2).astype(np.float32)
        return self._t, reward, True, False, {}


class Unpicklable(CartPoleEnv):
    """CartPole that refuses to be pickled, like envs holding simulator handles."""

    def __getstate__(self):
        raise TypeError("holds a simulator handle")


class ConstructorPickled(CartPoleEnv, EzPickle):
    """CartPole pickled as Gymnasium's MuJoCo and Box2D envs are: by its constructor's arguments
    alone, so an unpickled copy is a new env, not the one mid-episode."""

    def __init__(self, render_mode: str | None = None) -> None:
        CartPoleEnv.__init__(self, render_mode=render_mode)
        EzPickle.__init__(self, render_mode=render_mode)


class CrashOnce(CartPoleEnv):
    """CartPole whose process dies (os._exit, as a segfaulting simulator would) at its 150th
    step, once per marker file named by $RELAYRL_CRASH_MARKER: the first env to create the
    file crashes, every later one (a restarted actor's) runs normally."""

    def __init__(self, render_mode: str | None = None) -> None:
        super().__init__(render_mode=render_mode)
        self.steps = 0

    def step(self, action):
        self.steps += 1
        marker = os.environ.get("RELAYRL_CRASH_MARKER")
        if marker and self.steps == 150:
            try:
                os.close(os.open(marker, os.O_CREAT | os.O_EXCL))
            except FileExistsError:
                pass
            else:
                os._exit(1)
        return super().step(action)


class Broken(Countdown):
    """Countdown whose step raises, as a simulator's error would."""

    def step(self, action):
        raise ValueError("the simulator lost its state")


class BrokenAt(Countdown):
    """Countdown whose `at`-th step (counted over episodes) raises, as a flaky simulator's
    would; `at=0` never. `continuous`: a Box action (for SAC)."""

    def __init__(self, at: int = 0, continuous: bool = False, **kwargs) -> None:
        super().__init__(**kwargs)
        self.at, self.steps = at, 0
        if continuous:
            self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def step(self, action):
        self.steps += 1
        if self.steps == self.at:
            raise RuntimeError("simulator lost connection")
        return super().step(action)


class ResetBreaksAt(Countdown):
    """Countdown whose `at`-th reset raises, as a simulator that fails to restart would; `at=0` never."""

    def __init__(self, at: int = 0, **kwargs) -> None:
        super().__init__(**kwargs)
        self.at, self.resets = at, 0

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        self.resets += 1
        if self.resets == self.at:
            raise RuntimeError("simulator refused to reset")
        return super().reset(seed=seed, options=options)


class ShapeShifts(BrokenAt):
    """Countdown whose observations turn `late` from its `at`-th step on: "wider" (3,), "scalar"
    (a float32 NumPy scalar) or "row" ([1, 2]: NumPy would broadcast the last two into (2,))."""

    def __init__(self, late: str = "wider", **kwargs) -> None:
        super().__init__(**kwargs)
        self.late = late

    def step(self, action):
        self.steps += 1
        obs, reward, terminated, truncated, info = Countdown.step(self, action)
        if self.steps >= self.at:
            obs = {"wider": np.zeros(3, np.float32), "scalar": np.float32(0.4), "row": obs[None]}[self.late]
        return obs, reward, terminated, truncated, info


class KeyLost(BrokenAt):
    """Countdown in a Dict {"x": its Box, "y": Discrete(2)} whose observations lose "y" from its
    `at`-th step on."""

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.observation_space = gym.spaces.Dict({"x": self.observation_space, "y": gym.spaces.Discrete(2)})

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = super().reset(seed=seed, options=options)
        return {"x": obs, "y": 0}, info

    def step(self, action):
        self.steps += 1
        obs, reward, terminated, truncated, info = Countdown.step(self, action)
        return {"x": obs} if self.steps >= self.at else {"x": obs, "y": 1}, reward, terminated, truncated, info


class CastsAt(BrokenAt):
    """Countdown in a uint8 Box (with `entry`, the entry of that name of a Dict) whose observations
    come as int64 (values it keeps) and, from its `at`-th step on, as `late`: "fraction" (float32
    halves), "negative" (int64 below 0) or "list" (a list holding 300)."""

    def __init__(self, at: int = 0, late: str = "fraction", entry: str = "", **kwargs) -> None:
        super().__init__(at=at, **kwargs)
        box = gym.spaces.Box(0, 255, (2,), np.uint8)
        self.observation_space = gym.spaces.Dict({entry: box}) if entry else box
        self.late, self.entry = late, entry

    def _wrap(self, obs):
        return {self.entry: obs} if self.entry else obs

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = super().reset(seed=seed, options=options)
        return self._wrap(obs.astype(np.int64)), info

    def step(self, action):
        self.steps += 1
        obs, reward, terminated, truncated, info = Countdown.step(self, action)
        late = {"fraction": lambda: obs + 0.5, "negative": lambda: obs.astype(np.int64) - 300,
                "list": lambda: [300, int(obs[1])]}[self.late]
        obs = late() if self.at and self.steps >= self.at else obs.astype(np.int64)
        return self._wrap(obs), reward, terminated, truncated, info


class Tupled(Countdown):
    """Countdown taking a tuple kwarg, which config.toml keeps as a list."""

    def __init__(self, dims: tuple = (2,), **kwargs) -> None:
        super().__init__(**kwargs)
        self.dims = tuple(dims)


class RefusedInWorker(Countdown):
    """Countdown that refuses to be made in a worker process, as a user's env refuses a bad
    setting with relayrl's UserError (a copy-specific resource, say)."""

    def __init__(self, render_mode=None):
        if multiprocessing.parent_process() is not None:
            from relayrl.errors import UserError

            raise UserError("this copy's simulator licence is missing")
        super().__init__(render_mode=render_mode)


class BrokenInWorker(Countdown):
    """Countdown whose step raises when it runs in a worker process."""

    def step(self, action):
        if multiprocessing.parent_process() is not None:
            raise ValueError("the simulator lost its state")
        return super().step(action)


class ShapeShiftsInWorker(Countdown):
    """Countdown whose observations turn (3,) when it runs in a worker process."""

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        if multiprocessing.parent_process() is not None:
            obs = np.zeros(3, np.float32)
        return obs, reward, terminated, truncated, info


class OddError(Exception):
    """An exception whose pickle does not rebuild it (two arguments, one message)."""

    def __init__(self, what: str, where: str) -> None:
        super().__init__(f"{what} at {where}")


class OddInWorker(Countdown):
    """Countdown whose step raises an OddError when it runs in a worker process."""

    def step(self, action):
        if multiprocessing.parent_process() is not None:
            raise OddError("the simulator lost its state", "step 1")
        return super().step(action)


class DiesInWorker(Countdown):
    """Countdown whose process dies at its first step when it runs in a worker process."""

    def step(self, action):
        if multiprocessing.parent_process() is not None:
            os._exit(3)
        return super().step(action)


class _Slowed(Countdown):
    """Countdown of `LENGTH`-step episodes whose step sleeps `SLEEP` s (only in a worker
    process when `WORKER_ONLY`)."""

    LENGTH, SLEEP, WORKER_ONLY = 3, 0.0, False

    def __init__(self, render_mode: str | None = None) -> None:
        super().__init__(length=self.LENGTH, render_mode=render_mode)

    def step(self, action):
        if not self.WORKER_ONLY or multiprocessing.parent_process() is not None:
            time.sleep(self.SLEEP)
        return super().step(action)


class SlowInWorker(_Slowed):
    """1,000-step episodes whose step takes 0.3 s in a worker process."""

    LENGTH, SLEEP, WORKER_ONLY = 1000, 0.3, True


class Sleepy(_Slowed):
    """200-step episodes whose step sleeps 2 ms: a run that spends its time in env steps."""

    LENGTH, SLEEP = 200, 0.002


class KeepsAction(gym.Env):
    """Continuous env that keeps the action array it was given: reward -|a - previous a|."""

    def __init__(self, render_mode: str | None = None) -> None:
        self.observation_space = gym.spaces.Box(-1, 1, (1,), np.float32)
        self.action_space = gym.spaces.Box(-1, 1, (1,), np.float32)
        self.previous = np.zeros(1, np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        return np.zeros(1, np.float32), {}

    def step(self, action):
        reward = -float(np.abs(action - self.previous).sum())
        self.previous = action  # no copy, as an env may
        return np.zeros(1, np.float32), reward, False, False, {}


class Doubles(gym.ActionWrapper):
    """An action wrapper that scales in place, as a user's may: `a *= 2`."""

    def action(self, action):
        action *= 2.0
        return action


def doubled_keeps_action(**kwargs) -> gym.Env:
    return Doubles(KeepsAction(**kwargs))


class GlobalDraws(Countdown):
    """Countdown whose observation is a draw from the global `np.random`, as older envs do."""

    def __init__(self, render_mode: str | None = None) -> None:
        super().__init__(length=1000, render_mode=render_mode)

    def step(self, action):
        _, reward, terminated, truncated, info = super().step(action)
        return np.array([np.random.random(), self.t], np.float32), reward, terminated, truncated, info


class Ticking(_Slowed):
    """Episodes that never end in a test (10**9 steps), steps that sleep 0.5 ms: obs[0] counts
    every step a copy took."""

    LENGTH, SLEEP = 10**9, 0.0005


class IntAction(gym.Env):
    """An int64 Box action; reward = the action's value mod 7, obs[0] = 1 when it came as an int."""

    def __init__(self, render_mode: str | None = None) -> None:
        self.observation_space = gym.spaces.Box(-1, 1, (1,), np.float32)
        self.action_space = gym.spaces.Box(0, 10**9, (1,), np.int64)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        return np.zeros(1, np.float32), {}

    def step(self, action):
        a = np.asarray(action)
        return np.array([float(a.dtype.kind == "i")], np.float32), float(a[0] % 7), False, False, {}


class BigState(Countdown):
    """Countdown of 1,000-step episodes carrying 16 MB of data: its get_state replies are large,
    so reading one from a worker takes many reads."""

    def __init__(self, render_mode: str | None = None) -> None:
        super().__init__(length=1000, render_mode=render_mode)
        self.blob = np.random.default_rng(0).integers(0, 255, 16_000_000, dtype=np.uint8)


class Endless(Countdown):
    """Countdown that never ends an episode (no termination, no time limit of its own)."""

    def step(self, action):
        obs, reward, _, _, info = super().step(action)
        return obs, reward, False, False, info


class Sloppy(Countdown):
    """Countdown whose reset ignores its seed: Gymnasium's env checker complains about it."""

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        self.t = 0
        return np.array([self.t, 0], np.float32), {}


class Maskable(Countdown):
    """Countdown with MaskablePPO's masks: `action_masks()` (action 1 invalid on odd steps)."""

    def action_masks(self) -> np.ndarray:
        return np.array([True, self.t % 2 == 0])


class MaskInInfo(Countdown):
    """Countdown that gives its mask only as `info["action_mask"]`."""

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, _ = super().reset(seed=seed, options=options)
        return obs, {"action_mask": np.array([1, 1], np.int8)}


def double_reward(env: gym.Env) -> gym.Env:
    """An env.wrappers entry: rewards times 2."""
    return gym.wrappers.TransformReward(env, lambda r: 2 * r)


def refuses_the_env(env: gym.Env) -> gym.Env:
    """An env.wrappers entry that fails on the env it wraps (FlattenObservation over a Text entry)."""
    raise NotImplementedError(f"this wrapper cannot wrap {env}")


def shift_obs(env: gym.Env) -> gym.Env:
    """An env.wrappers entry: observations + 100 (applied after double_reward, order shows)."""
    return gym.wrappers.TransformObservation(env, lambda o: o + 100, env.observation_space)


def make_countdown(length: int = 3, render_mode: str | None = None) -> gym.Env:
    """A factory function (not a class) named in env.id."""
    return Countdown(length=length, render_mode=render_mode)


# Gymnasium's `module:EnvId-v0` form: importing this module registers the id.
if "ToyCountdown-v0" not in gym.registry:
    gym.register("ToyCountdown-v0", entry_point="toy_envs:Countdown", kwargs={"length": 2})


class NonFiniteAt(Countdown):
    """Countdown of 20-step episodes whose `what` ("reward" or "obs") turns NaN (or `value`) at
    this copy's `at`-th step, counted over episodes. `continuous`: a Box action (for SAC)."""

    def __init__(self, at: int = 50, what: str = "reward", value: float = float("nan"), continuous: bool = False,
                 render_mode: str | None = None) -> None:
        super().__init__(length=20, render_mode=render_mode)
        self.at, self.what, self.value, self.steps = at, what, value, 0
        if continuous:
            self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        self.steps += 1
        if self.steps >= self.at:
            if self.what == "reward":
                reward = self.value
            elif self.what == "obs64":  # a float64 observation, cast to the space's float32 by relayrl
                obs = np.full(obs.shape, self.value)
            else:
                obs = np.full_like(obs, self.value)
        return obs, reward, terminated, truncated, info


class FourValueStep(Countdown):
    """The old Gym API: `step` returns (obs, reward, done, info)."""

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        return obs, reward, terminated or truncated, info


class OldReset(Countdown):
    """The old Gym API: `reset(self)` takes no seed and returns the observation alone."""

    def reset(self):  # type: ignore[override]
        return super().reset()[0]


class SeedOnlyReset(Countdown):
    """`reset(self, seed=None)`: no options, which Gymnasium's wrappers (a TimeLimit's) pass on."""

    def reset(self, seed: int | None = None):  # type: ignore[override]
        return super().reset(seed=seed)


def time_limited_seed_only_reset() -> gym.Env:
    return gym.wrappers.TimeLimit(SeedOnlyReset(), 50)


class BareReset(Countdown):
    """Half the old Gym API: `reset` takes a seed but returns the observation alone."""

    def reset(self, *, seed: int | None = None, options: dict | None = None):  # type: ignore[override]
        return super().reset(seed=seed, options=options)[0]


class ArrayReward(Countdown):
    """Rewards as one-element arrays, np.array([1.0]), not numbers."""

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        return obs, np.array([reward]), terminated, truncated, info


class BuggyInit(Countdown):
    """A constructor with a bug of its own: a helper called with an argument too many."""

    def __init__(self, length: int = 3, **kwargs) -> None:
        super().__init__(length=length, **kwargs)
        self.grid = self._grid(length, 3)

    def _grid(self, length: int) -> list[int]:
        return [0] * length


class NeedsSize(Countdown):
    """A constructor with a required argument."""

    def __init__(self, size: int, **kwargs) -> None:
        super().__init__(length=size, **kwargs)


class NoneReward(Countdown):
    """Rewards as None (a step() that forgot to compute one): NumPy would store NaN."""

    def step(self, action):
        obs, _, terminated, truncated, info = super().step(action)
        return obs, None, terminated, truncated, info


class TextReward(Countdown):
    """Rewards as text, "1.0": NumPy would parse it."""

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        return obs, str(reward), terminated, truncated, info


class NoActionSpace(Countdown):
    """An env that forgot to set its action_space."""

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        del self.action_space


class WrongShapeObs(Countdown):
    """Observations of shape (3,) float64 where the space says (2,) float32."""

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = super().reset(seed=seed, options=options)
        return np.zeros(3), info

    def step(self, action):
        _, reward, terminated, truncated, info = super().step(action)
        return np.zeros(3), reward, terminated, truncated, info


class Float64Obs(Countdown):
    """Observations of the space's shape but float64 where it says float32: harmless (cast)."""

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = super().reset(seed=seed, options=options)
        return obs.astype(np.float64), info

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        return obs.astype(np.float64), reward, terminated, truncated, info


class SloppyFloat64(Float64Obs, Sloppy):
    """Sloppy whose observations are float64 where its space says float32, as a simulator's are."""


class NoRender(Countdown):
    """An env whose render() returns None (no rgb_array frames)."""

    def render(self):
        return None


class RenderRaises(Countdown):
    """An env whose render() fails (as one needing a display does on a headless machine)."""

    def render(self):
        raise RuntimeError("no display")


class NoRenderMethod(Countdown):
    """An env that leaves render() as gymnasium.Env has it (NotImplementedError, no message)."""

    render = gym.Env.render


class NoRenderMode(gym.Env):
    """An env class whose __init__ takes no render_mode."""

    def __init__(self) -> None:
        self.observation_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.action_space = gym.spaces.Discrete(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(1, np.float32), {}

    def step(self, action):
        return np.zeros(1, np.float32), 0.0, True, False, {}


class Repeated(gym.ObservationWrapper):
    """An env's Box observation repeated: twice as many numbers (another network input size)."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        low, high = np.tile(env.observation_space.low, 2), np.tile(env.observation_space.high, 2)
        self.observation_space = gym.spaces.Box(low, high, dtype=np.float32)

    def observation(self, obs):
        return np.tile(obs, 2).astype(np.float32)


INTERRUPT = {"now": False}  # set by a test: the next step of an Interrupting env raises KeyboardInterrupt


class Interrupting(Countdown):
    """Countdown whose step is Ctrl-C once a test sets INTERRUPT["now"] (the final evaluation's)."""

    def step(self, action):
        if INTERRUPT["now"]:
            INTERRUPT["now"] = False
            raise KeyboardInterrupt
        return super().step(action)


class MadeOnlyInTheDriver(Countdown):
    """A Countdown that a Ray worker cannot make: a stand-in for a module its node lacks."""

    def __init__(self, render_mode: str | None = None) -> None:
        import ray

        if ray.is_initialized() and ray.get_runtime_context().worker.mode == ray.WORKER_MODE:
            from relayrl.errors import UserError

            raise UserError("no module 'remoteonly' on this node (the test's stand-in)")
        super().__init__(render_mode=render_mode)


class NarrowBox(gym.Env):
    """A Box(0.1, 0.3) action in `dtype`; obs[0] = 1 when the action was inside the space, obs[1]
    the action as given (float32 rounds each bound to a value just past it on one side)."""

    def __init__(self, dtype: str = "float32", render_mode: str | None = None) -> None:
        self.observation_space = gym.spaces.Box(-1, 1, (2,), np.float64)
        self.action_space = gym.spaces.Box(0.1, 0.3, (1,), np.dtype(dtype))

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        return np.zeros(2), {}

    def step(self, action):
        inside = self.action_space.contains(np.asarray(action))
        return np.array([float(inside), float(np.asarray(action)[0])]), 0.0, False, False, {}


class CloseRaises(Countdown):
    """Countdown whose close() raises (a simulator's teardown bug), counting the copies closed."""

    closed = 0

    def close(self):
        CloseRaises.closed += 1
        raise RuntimeError("the simulator's socket was already gone")


class SlowStart(gym.Env):
    """Takes `delay` seconds to make in a worker process (at once in the main one)."""

    observation_space = gym.spaces.Box(-1, 1, (1,), np.float32)
    action_space = gym.spaces.Discrete(2)

    def __init__(self, delay: float = 30.0, render_mode: str | None = None) -> None:
        import multiprocessing
        import time

        if multiprocessing.parent_process() is not None:
            time.sleep(delay)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        return np.zeros(1, np.float32), {}

    def step(self, action):
        return np.zeros(1, np.float32), 0.0, False, False, {}


class DiesBeforeItStarts(Countdown):
    """Countdown whose process dies as it makes the env in a worker process (as a spawned worker
    re-running an unguarded script's top level does, before its first answer)."""

    def __init__(self, **kwargs) -> None:
        if multiprocessing.parent_process() is not None:
            os._exit(1)
        super().__init__(**kwargs)


class UnpicklableInWorker(Countdown):
    """Countdown that cannot be pickled in a worker process (a simulator handle of its own there)."""

    def __getstate__(self):
        if multiprocessing.parent_process() is not None:
            raise TypeError("cannot pickle the simulator's handle")
        return self.__dict__
