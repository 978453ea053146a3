"""The lines relayrl prints for its user (on stderr), and `quiet`, which keeps one call's lines
back: `relayrl.train(..., quiet=True)` in a sweep's trials. Per thread (a context variable), so
one Optuna thread's quiet run leaves another's lines and the process's stderr alone, where
`contextlib.redirect_stderr` swaps sys.stderr for every thread."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator
from contextvars import ContextVar

_QUIET: ContextVar[bool] = ContextVar("relayrl_quiet", default=False)


def say(text: str) -> None:
    """One line for the user, unless inside `quiet(True)`."""
    if not _QUIET.get():
        print(text, file=sys.stderr, flush=True)


@contextlib.contextmanager
def quiet(on: bool = True) -> Iterator[None]:
    """`say` prints nothing inside (where `on`)."""
    token = _QUIET.set(on or _QUIET.get())
    try:
        yield
    finally:
        _QUIET.reset(token)
