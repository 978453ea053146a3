"""pybullet's Minitaur quadruped (`MinitaurBulletEnv`, as in TF-Agents' SAC tutorial) on Gymnasium's API.

pybullet ships the env in `pybullet_envs.bullet.minitaur_gym_env`, but `pybullet_envs/__init__.py`
imports the old `gym` package, and the env module itself imports `gym` (for `Env`, `spaces` and
`seeding`) and `pkg_resources` (gone from setuptools >= 81). We load the module and its siblings
from pybullet's folder under a private package name, so neither package `__init__.py` runs, and
answer those imports with gymnasium's equivalents only while the import runs.

Episodes end (`terminated`) when the robot falls; the 1000-step limit is Gymnasium's `TimeLimit`
from the registration (`relayrl/MinitaurBullet-v0`), so it reads as truncation. The underlying env
never ends an episode on a step count: its `_termination` is "fallen, or farther than
`distance_limit`" (infinite by default).
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import io
import os
import sys
import threading
import types
import warnings
from typing import Any

import gymnasium as gym
import numpy as np

from relayrl.envs.legacy_gym import importing_without_gym
from relayrl.errors import UserError, install

ENV_ID = "relayrl/MinitaurBullet-v0"
_PACKAGE = "_relayrl_pybullet_bullet"  # private name for pybullet_envs/bullet, loaded without its __init__
_load_lock = threading.Lock()
_module: types.ModuleType | None = None


def _parse_version(version: str) -> tuple[int, ...]:
    return tuple(int(part) for part in version.split(".") if part.isdigit())


def _minitaur_gym_env() -> types.ModuleType:
    """pybullet's `minitaur_gym_env` module, imported once; UserError when pybullet is missing."""
    global _module
    missing = UserError(f"{ENV_ID} needs pybullet: {install('bullet')}")
    try:
        import pybullet  # noqa: F401
    except ImportError:
        raise missing from None
    # find_spec locates pybullet_envs without running its __init__ (which imports old gym).
    spec = importlib.util.find_spec("pybullet_envs")
    if spec is None or not spec.submodule_search_locations:
        raise missing
    with _load_lock:
        if _module is None:
            _module = _load_without_gym(os.path.join(list(spec.submodule_search_locations)[0], "bullet"))
    return _module


def _load_without_gym(bullet_dir: str) -> types.ModuleType:
    package = types.ModuleType(_PACKAGE)
    package.__path__ = [bullet_dir]  # relative imports (`from . import minitaur`) resolve in here
    # pkg_resources always shimmed: gone from setuptools >= 81, and a deprecation warning where it exists.
    pkg_resources: Any = types.ModuleType("pkg_resources")  # Any: ModuleType's type has no attributes to set
    pkg_resources.parse_version = _parse_version
    with importing_without_gym({_PACKAGE: package}, gym.Env, gym.Wrapper, {"pkg_resources": pkg_resources}):
        return importlib.import_module(f"{_PACKAGE}.minitaur_gym_env")


class _SeededRandomizer:
    """pybullet's MinitaurEnvRandomizer (same ranges, same order) drawing from our env's RNG.

    The original draws from the global `random` and `np.random`, so `reset(seed=...)` could not
    make the randomized masses, battery voltage, damping and foot friction reproducible.
    """

    def __init__(self, owner: MinitaurEnv, ranges: types.ModuleType) -> None:
        self._owner = owner
        self._r = ranges

    def randomize_env(self, env: Any) -> None:
        rng, r, robot = self._owner.np_random, self._r, env.minitaur
        base_mass = robot.GetBaseMassFromURDF()
        lo, hi = r.MINITAUR_BASE_MASS_ERROR_RANGE
        robot.SetBaseMass(rng.uniform(base_mass * (1.0 + lo), base_mass * (1.0 + hi)))
        leg_masses = np.asarray(robot.GetLegMassesFromURDF())
        lo, hi = r.MINITAUR_LEG_MASS_ERROR_RANGE
        robot.SetLegMasses([rng.uniform(m * (1.0 + lo), m * (1.0 + hi)) for m in leg_masses])
        robot.SetBatteryVoltage(rng.uniform(*r.BATTERY_VOLTAGE_RANGE))
        robot.SetMotorViscousDamping(rng.uniform(*r.MOTOR_VISCOUS_DAMPING_RANGE))
        robot.SetFootFriction(rng.uniform(*r.MINITAUR_LEG_FRICTION))


class MinitaurEnv(gym.Env[np.ndarray, np.ndarray]):
    """Minitaur walking forward: obs = 8 motor angles, 8 velocities, 8 torques, base quaternion.

    Action: 8 values in [-1, 1], pybullet's leg model: [0:4] extend and [4:8] swing the four legs,
    mapped to the 8 motor angles; values beyond 1.01 in size raise pybullet's ValueError. Reward
    per step: forward (x) displacement of the base minus 0.005 * |torque . velocity| * 0.002 s.
    """

    # One env step is 5 physics substeps of 2 ms: 100 steps per simulated second.
    metadata = {"render_modes": ["rgb_array"], "render_fps": 100}

    def __init__(self, render_mode: str | None = None) -> None:
        if render_mode not in (None, "rgb_array"):
            raise UserError(f"{ENV_ID}: render_mode={render_mode!r} is not supported (valid: 'rgb_array' or None)")
        module = _minitaur_gym_env()
        ranges = sys.modules[f"{_PACKAGE}.minitaur_env_randomizer"]
        self.render_mode = render_mode
        # The constructor prints "urdf_root=..." and builds float64-bounded Boxes we replace below
        # (gymnasium warns about the cast). render=False: DIRECT mode, no GUI.
        with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*precision lowered by casting", category=UserWarning)
            self._env = module.MinitaurBulletEnv(render=False, env_randomizer=_SeededRandomizer(self, ranges))
        robot = self._env.minitaur
        eps = module.OBSERVATION_EPS
        high = (robot.GetObservationUpperBound() + eps).astype(np.float32)
        low = (robot.GetObservationLowerBound() - eps).astype(np.float32)
        self.observation_space = gym.spaces.Box(low, high, dtype=np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (8,), dtype=np.float32)
        self._closed = False

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)  # reseeds self.np_random, which the randomizer draws from
        obs = self._env.reset()  # hard reset: a fresh simulation, so equal seeds give equal episodes
        return np.asarray(obs, dtype=np.float32), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        obs, reward, fallen, _ = self._env.step(np.asarray(action, dtype=np.float32))
        return np.asarray(obs, dtype=np.float32), float(reward), bool(fallen), False, {}

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        # 720x960 through pybullet's CPU TinyRenderer (DIRECT mode has no OpenGL context).
        return np.ascontiguousarray(np.asarray(self._env.render(mode="rgb_array"))[:, :, :3], dtype=np.uint8)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._env._pybullet_client.disconnect()
