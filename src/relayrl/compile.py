"""The numba gate: where a module has a compiled twin (`x_fast.py` beside `x.py`), callers
ask `compiled(...)` for it and take their NumPy path on None.

numba is the optional `relayrl[fast]` extra. `RELAYRL_NUMBA=0` turns every twin off (tests
and benchmarks compare the two paths, which give the same results).
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Callable
from typing import Any


def compiled(module: str, name: str) -> Any:
    """`module.name` from a compiled twin (a dotted module path, e.g. "relayrl.replay.sumtree_fast"),
    or None without numba or with `RELAYRL_NUMBA=0`."""
    if os.environ.get("RELAYRL_NUMBA", "1") == "0":
        return None
    try:
        return getattr(importlib.import_module(module), name)
    except ImportError:  # no numba
        return None


def njit(fn: Callable[..., Any]) -> Any:
    """numba.njit, cached on disk where numba finds a writable cache directory; without one
    (read-only install, no home), compiled per process. Imports numba, so a twin module that
    uses it fails to import without numba, which `compiled` reads as "no twin"."""
    import numba

    try:
        return numba.njit(cache=True)(fn)
    except RuntimeError:  # numba: "cannot cache function ...: no locator available"
        return numba.njit(fn)
