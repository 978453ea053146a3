"""Super Mario Bros (gym-super-mario-bros 7.4.0 on nes-py 8.2.1, the `[mario]` extra) on Gymnasium's API.

Both packages target the old `gym` API, and nes-py 8.2.1 predates NumPy 2. We never import `gym`:
nes-py's `nes_env.py` and `wrappers/joypad_space.py` and gym-super-mario-bros' `smb_env.py` are
loaded under private package names with `gym` answered by a small shim while they import (they use
only `gym.Env`, `gym.Wrapper` and `gym.spaces`), so neither package `__init__.py` (which registers
old-gym ids) runs, and the real `nes_py` / `gym_super_mario_bros` modules, if anyone imports them,
stay untouched. The NumPy-2 fixes below patch our private copies only.

`relayrl/SuperMarioBros-1-1-v0` is gym-super-mario-bros' `SuperMarioBros-1-1-v0` (vanilla ROM, which
the package ships: nothing is downloaded): one step = one NES frame, obs [240, 256, 3] uint8, the
Mario tutorial's actions [right] and [right, A], reward = x progress + clock penalty - 25 on death
(clipped to [-15, 15]), `terminated` on death or flag. `make_preprocessed` adds the tutorial's
pixel stack (skip 4, grayscale, 84x84, stack 4).
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
import threading
import types
from collections.abc import Sequence
from typing import Any, cast

import gymnasium as gym
import numpy as np

from relayrl.envs.legacy_gym import importing_without_gym
from relayrl.envs.pixels import mario_preprocessing
from relayrl.errors import UserError, install

ENV_ID = "relayrl/SuperMarioBros-1-1-v0"
PIXELS_ID = "relayrl/SuperMarioBros-1-1-pixels-v0"  # the preprocessed stack
INSTALL = install("mario")
TUTORIAL_ACTIONS: tuple[tuple[str, ...], ...] = (("right",), ("right", "A"))
# The level clock kills a dawdling Mario (a termination: the clock is on screen) within ~8,000
# frames (8,019 standing still); this only bounds episodes the clock would not end. Raw frames.
MAX_EPISODE_FRAMES = 10_000
_NES, _SMB = "_relayrl_nes_py", "_relayrl_gym_super_mario_bros"  # private names for the two packages
_load_lock = threading.Lock()
_modules: tuple[types.ModuleType, types.ModuleType] | None = None


class _LegacyEnv:
    """Stands in for `gym.Env` as NESEnv's base: the emulator keeps gym's 4-tuple API, so it must
    not pass for a Gymnasium env; MarioEnv wraps it instead."""

    spec = None  # read by NESEnv.render("human") only

    @property
    def unwrapped(self) -> _LegacyEnv:
        return self


class _LegacyWrapper(_LegacyEnv):
    """Stands in for `gym.Wrapper` as JoypadSpace's base (we use only its action map)."""

    def __init__(self, env: _LegacyEnv) -> None:
        self.env = env


def _package(name: str, real: str) -> types.ModuleType:
    """An empty package `name` whose submodules are `real`'s files (`real`'s __init__ never runs)."""
    spec = importlib.util.find_spec(real)  # locates the package without importing it
    if spec is None or not spec.submodule_search_locations:
        raise UserError(f"relayrl's Super Mario Bros envs ({ENV_ID} and the ddqn-mario preset's "
                        f"{PIXELS_ID}) need {real.replace('_', '-')}: {INSTALL}")
    package = types.ModuleType(name)
    package.__path__ = list(spec.submodule_search_locations)  # relative imports resolve in here
    return package


def _load() -> tuple[types.ModuleType, types.ModuleType]:
    """(our copy of smb_env, our copy of joypad_space), loaded once; UserError when the extra is missing."""
    global _modules
    with _load_lock:
        if _modules is None:
            _modules = _load_without_gym()
            _patch_for_numpy2(sys.modules[f"{_NES}._rom"].ROM, _modules[0].SuperMarioBrosEnv)
    return _modules


def _load_without_gym() -> tuple[types.ModuleType, types.ModuleType]:
    nes, smb = _package(_NES, "nes_py"), _package(_SMB, "gym_super_mario_bros")
    # smb_env does `from nes_py import NESEnv`: answer it with our copy while it imports.
    with importing_without_gym({_NES: nes, _SMB: smb}, _LegacyEnv, _LegacyWrapper, {"nes_py": nes}):
        cast(Any, nes).NESEnv = importlib.import_module(f"{_NES}.nes_env").NESEnv  # loads the C++ emulator (ctypes)
        joypad = importlib.import_module(f"{_NES}.wrappers.joypad_space")
        return importlib.import_module(f"{_SMB}.smb_env"), joypad


def _patch_for_numpy2(rom: Any, smb: Any) -> None:
    """Under NumPy 2 (NEP 50) `uint8 <op> python int` stays uint8: `header[4] * 16 * 2**10` raises
    "Python integer 1024 out of bounds for uint8", and RAM reads like `ram[0x6d] * 0x100` would too.
    NumPy 1 computed these in int64, so do the arithmetic on Python ints (same values as NumPy 1).
    `rom` and `smb` are classes, typed Any: a type's type has no attributes to set."""
    rom.header = property(lambda self: self.raw_data[:16].astype(np.int64))
    ram = lambda env, address: int(env.ram[address])  # noqa: E731
    smb._x_position = property(lambda self: ram(self, 0x6D) * 0x100 + ram(self, 0x86))
    smb._left_x_position = property(lambda self: (ram(self, 0x86) - ram(self, 0x071C)) % 256)
    smb._y_pixel = property(lambda self: ram(self, 0x03B8))
    smb._y_viewport = property(lambda self: ram(self, 0x00B5))


def _info(raw: dict[str, Any]) -> dict[str, Any]:
    """The emulator's info with NumPy scalars made Python values (they go to JSON logs)."""
    return {k: v if isinstance(v, str) else bool(v) if k == "flag_get" else int(v) for k, v in raw.items()}


class MarioEnv(gym.Env[np.ndarray, np.int64]):
    """One Super Mario Bros stage, one NES frame a step, on Gymnasium's API.

    info: x_pos, y_pos, flag_get, coins, life, score, stage, status, time, world. The emulator is
    deterministic (no randomness to seed): equal actions give equal episodes.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 60}

    def __init__(self, world: int = 1, stage: int = 1, actions: Sequence[Sequence[str]] = TUTORIAL_ACTIONS,
                 render_mode: str | None = None) -> None:
        if render_mode not in (None, "rgb_array"):
            raise UserError(f"{ENV_ID}: render_mode={render_mode!r} is not supported (valid: 'rgb_array' or None)")
        smb_env, joypad = _load()
        self.render_mode = render_mode
        # Runs the ROM past the title screen to the stage's start, then snapshots it for resets.
        self._env = smb_env.SuperMarioBrosEnv(rom_mode="vanilla", target=(world, stage))
        # JoypadSpace turns button lists into controller bytes; we step the emulator with the byte
        # ourselves, since JoypadSpace.step would hand back gym's 4-tuple.
        pad = joypad.JoypadSpace(self._env, [list(a) for a in actions])
        self._action_bytes = [pad._action_map[i] for i in range(len(actions))]
        self.action_meanings: list[str] = pad.get_action_meanings()
        self.action_space = gym.spaces.Discrete(len(actions))
        self.observation_space = gym.spaces.Box(0, 255, self._env.observation_space.shape, dtype=np.uint8)

    def _screen(self) -> np.ndarray:
        # A copy: `screen` is a view of the emulator's BGRx frame buffer, rewritten every frame.
        # Its channel stride is -1, which makes np.ascontiguousarray several times slower than
        # copying channel by channel.
        screen = self._env.screen
        frame = np.empty(screen.shape, dtype=np.uint8)
        for c in range(screen.shape[-1]):
            frame[..., c] = screen[..., c]
        return frame

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self._env.reset()  # restores the snapshot taken at the stage's start
        return self._screen(), _info(self._env._get_info())

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        _, reward, done, info = self._env.step(self._action_bytes[int(action)])
        return self._screen(), float(reward), bool(done), False, _info(info)

    def render(self) -> np.ndarray | None:
        return self._screen() if self.render_mode == "rgb_array" else None

    def __getstate__(self) -> dict:
        # Pickle would succeed and copy the C++ emulator's address as a plain int: the copy would
        # drive the original's emulator (or a dangling pointer in another process). Raising
        # TypeError opts out of checkpoint snapshots (envs/gym.py env_snapshot) and copy.deepcopy.
        raise TypeError(f"{ENV_ID}: the NES emulator's state cannot be pickled")

    def close(self) -> None:
        if getattr(self, "_env", None) is not None and self._env._env is not None:
            self._env.close()  # frees the C++ emulator; NESEnv.close raises when called twice


def make_preprocessed(render_mode: str | None = None, max_episode_frames: int = MAX_EPISODE_FRAMES,
                      **preprocessing: Any) -> gym.Env:
    """The Mario tutorial's env: MarioEnv, then skip 4 (summed rewards), grayscale, 84x84, stack 4
    (uint8 [4, 84, 84]; keyword overrides: skip, screen_size, stack, max_pool). The time limit sits
    under the frame skip, so it counts frames. `render()` gives full RGB frames."""
    env = gym.wrappers.TimeLimit(MarioEnv(render_mode=render_mode), max_episode_frames)
    return mario_preprocessing(env, **preprocessing)


def _rom_path() -> str:
    """Where the vanilla ROM lies inside the installed package (for tests: nothing is downloaded)."""
    smb_env, _ = _load()
    assert smb_env.__file__ is not None  # a module imported from its file
    return os.path.join(os.path.dirname(smb_env.__file__), "_roms", "super-mario-bros.nes")
