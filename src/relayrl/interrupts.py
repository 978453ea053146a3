"""Ctrl-C, SIGTERM and SIGHUP handled where stopping at once would lose work: `deferred` holds
them until a file is written; `stop_request` turns the first into a request that the training
loop honours at the end of its iteration, so the run stops with a checkpoint."""

from __future__ import annotations

import contextlib
import os
import signal
import stat
import sys
import threading
from collections.abc import Callable, Iterator
from typing import Any

from relayrl.streams import to_devnull

HANGUP: int | None = getattr(signal, "SIGHUP", None)  # the terminal closed (an SSH session lost); not on Windows
# delivered in this order: the exception of the last, SIGTERM's or SIGHUP's, wins
WANTED: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM, *([HANGUP] if HANGUP is not None else []))


def heard(signum: int) -> None:
    """What every handler here does first: after SIGHUP, stdout and stderr that were the closed
    terminal, or a pipe (whose reader, `| tee log`, ends with the terminal), write to /dev/null,
    so that the stop's own lines (which no one can read) do not fail it with EIO or EPIPE before
    the checkpoint is written. A file stays, and so does a terminal still open (`kill -HUP`)."""
    if signum != HANGUP:
        return
    for fd in (1, 2):
        with contextlib.suppress(OSError):
            mode = os.fstat(fd).st_mode
            # a closed terminal: still a character device, but no longer a tty (/dev/null is neither)
            if stat.S_ISFIFO(mode) or stat.S_ISCHR(mode) and not os.isatty(fd) and not _is_null(fd):
                to_devnull(fd)


def _is_null(fd: int) -> bool:
    return os.fstat(fd).st_rdev == os.stat(os.devnull).st_rdev


def _handlers() -> dict[int, Any] | None:
    """The current handlers of the signals whose handlers can be swapped, or None off the main
    thread (only it handles signals). A handler not set from Python (None) could not be put
    back: that signal is left as it is, the others are still handled."""
    if threading.current_thread() is not threading.main_thread():
        return None
    return {s: h for s in WANTED if (h := signal.getsignal(s)) is not None}


@contextlib.contextmanager
def deferred(until: str = "the file being written is complete") -> Iterator[None]:
    """SIGINT, SIGTERM and SIGHUP received inside wait for its end, then act as they would have. An
    interrupt raised inside a writer (torch's zip writer) made it fail with an error of its own
    instead, and the clean stop became a traceback. Only the main thread handles signals.
    `until`: what the stop waits for, as the line printed at the first signal says."""
    previous = _handlers()
    if previous is None:
        yield
        return
    pending: list[int] = []

    def hold(signum: int, frame: object) -> None:
        heard(signum)
        if not _Deferring.said:  # a large checkpoint takes a while: say why the stop waits, once
            print(f"relayrl: stopping once {until}", file=sys.stderr, flush=True)
            _Deferring.said = True
        pending.append(signum)

    _Deferring.depth += 1  # a write inside a write (a checkpoint's file) holds a signal twice
    try:
        _install({sig: hold for sig, h in previous.items() if h != signal.SIG_IGN})  # nohup's SIGHUP stays ignored
        yield
    finally:
        _Deferring.depth -= 1
        if _Deferring.depth == 0:
            _Deferring.said = False
        _install(previous)
        _deliver([sig for sig in WANTED if sig in pending], previous)


class _Deferring:
    """Across nested `deferred` blocks (the main thread's only): how deep, and whether the wait was said."""

    depth = 0
    said = False


def _deliver(signals: list[int], handlers: dict[int, Any]) -> None:
    """Act on each signal as its own handler would have, every one even if one raises."""
    if not signals:
        return
    sig, rest = signals[0], signals[1:]
    try:
        handler = handlers[sig]
        if callable(handler):
            handler(sig, None)
        elif handler == signal.SIG_DFL:
            signal.raise_signal(sig)
    finally:
        _deliver(rest, handlers)


def _install(handlers: dict[int, Any]) -> None:
    """Put `handlers` in place; no signal lands between two of the swaps (POSIX masks them meanwhile)."""
    masking = hasattr(signal, "pthread_sigmask")
    old = signal.pthread_sigmask(signal.SIG_BLOCK, WANTED) if masking else None
    try:
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    finally:
        if old is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)


@contextlib.contextmanager
def stop_request(on_signal: Callable[[int], None], signals: tuple[int, ...] = WANTED) -> Iterator[None]:
    """Inside, the first of `signals` (SIGINT, SIGTERM, SIGHUP) only calls `on_signal(signum)` (a second
    acts as it would have, at once): the caller stops at a safe point, saves, then calls
    `redeliver`, so the process ends as the signal asked. A signal that is ignored (SIGINT in
    a background job) stays ignored; where handlers cannot be swapped nothing changes."""
    previous = _handlers()
    if previous is None:
        yield
        return

    def record(signum: int, frame: object) -> None:
        heard(signum)
        _install(previous)  # a second signal is not held back
        on_signal(signum)

    try:
        _install({sig: record for sig in signals if sig in previous and previous[sig] != signal.SIG_IGN})
        yield
    finally:
        _install(previous)


def again(signum: int) -> str:
    """What stops at once after the signal `stop_request` held back: the words for the console."""
    return "Ctrl-C again stops at once" if signum == signal.SIGINT else "a second signal stops at once"


def redeliver(signum: int, message: str = "") -> None:
    """Act on a signal that `stop_request` recorded as its handler, now back in place, would;
    Python's own Ctrl-C handler's KeyboardInterrupt carries `message` (what a notebook shows)."""
    handler = signal.getsignal(signum)
    if handler is signal.default_int_handler:
        raise KeyboardInterrupt(message)
    _deliver([signum], {signum: handler})
