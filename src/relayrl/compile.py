"""The numba gate: where a module has a compiled twin (`x_fast.py` beside `x.py`), callers
import it, inside a function, only where `numba_available()`, and take their NumPy path
otherwise. The import stays a plain import statement, so a reader (and the import-graph
test) can follow it.

numba is the optional `relayrl[fast]` extra. `RELAYRL_NUMBA=0` turns every twin off (tests
and benchmarks compare the two paths, which give the same results).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any


def numba_available() -> bool:
    """True where the compiled twins run: numba imports and `RELAYRL_NUMBA` is not 0 (read at
    every call, so a test can switch it)."""
    if os.environ.get("RELAYRL_NUMBA", "1") == "0":
        return False
    try:
        import numba  # noqa: F401
    except ImportError:
        return False
    return True


def njit(fn: Callable[..., Any]) -> Any:
    """numba.njit, cached on disk where numba finds a writable cache directory; without one
    (read-only install, no home), compiled per process."""
    import numba

    try:
        return numba.njit(cache=True)(fn)
    except RuntimeError:  # numba: "cannot cache function ...: no locator available"
        return numba.njit(fn)
