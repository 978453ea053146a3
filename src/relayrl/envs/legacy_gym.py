"""Importing modules written for the old `gym` package (nes-py's, pybullet's) without importing it."""

from __future__ import annotations

import contextlib
import sys
import types
from collections.abc import Iterator
from typing import Any

import gymnasium as gym


class _GymShim(types.ModuleType):
    """What those modules use of old `gym`: Env, Wrapper, spaces, utils.seeding, and __version__
    (pybullet's only compares it with 0.9.6, to skip pre-0.9.6 method aliases)."""

    def __init__(self, env: type, wrapper: type) -> None:
        super().__init__("gym")
        self.Env, self.Wrapper, self.spaces = env, wrapper, gym.spaces
        utils: Any = types.ModuleType("gym.utils")  # Any: ModuleType's type has no attributes to set
        utils.seeding = gym.utils.seeding
        self.utils = utils
        self.__version__ = "0.26.2"


@contextlib.contextmanager
def importing_without_gym(packages: dict[str, types.ModuleType], env: type, wrapper: type,
                          shims: dict[str, types.ModuleType]) -> Iterator[None]:
    """While the body imports from `packages` (kept in sys.modules under their private names):
    a `gym` whose Env and Wrapper are `env` and `wrapper`, and `shims`, answer their imports, and
    are taken out after, with sys.path as it was (pybullet's module puts site-packages first when
    it runs). A failure takes the packages' half-imported modules out too."""
    gym_shim = _GymShim(env, wrapper)
    shims = {"gym": gym_shim, "gym.spaces": gym.spaces, "gym.utils": gym_shim.utils, **shims}
    saved = {name: sys.modules.get(name) for name in shims}
    saved_path = list(sys.path)
    sys.modules.update(shims)
    sys.modules.update(packages)
    try:
        yield
    except BaseException:
        for name in [n for n in sys.modules if n.split(".")[0] in packages]:
            del sys.modules[name]
        raise
    finally:
        sys.path[:] = saved_path
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module
