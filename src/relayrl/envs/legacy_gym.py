"""Importing modules written for the old `gym` package (nes-py's, pybullet's) without importing it."""

from __future__ import annotations

import contextlib
import sys
import types
from collections.abc import Iterator


@contextlib.contextmanager
def importing_without_gym(packages: dict[str, types.ModuleType], shims: dict[str, types.ModuleType]) -> Iterator[None]:
    """While the body imports from `packages` (kept in sys.modules under their private names):
    `shims` answer the imports of old `gym` and its kin, and are taken out after, with sys.path
    as it was (pybullet's module puts site-packages first when it runs). A failure takes the
    packages' half-imported modules out too."""
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
