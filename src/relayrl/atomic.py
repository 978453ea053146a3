"""Files written atomically: a reader, or a run that crashes mid-write, sees the old file or the
new one, never a partial file, and a failed write leaves no temp file behind."""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any


@contextlib.contextmanager
def replacing(path: Path, tmp_name: str | None = None) -> Iterator[Path]:
    """Yields a temp path beside `path`; on success it is renamed over `path` and the folder
    synced, on failure removed. `tmp_name` for writers that want a given suffix."""
    path = Path(path)
    tmp = path.with_name(tmp_name or path.name + ".tmp")  # never matches a glob for the real suffix
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    _fsync_folder(path.parent)


def write_with(path: Path, write: Callable[[IO[bytes]], Any], tmp_name: str | None = None) -> None:
    """Call `write(file)` on a temp file, fsync it, rename it over `path`. Ctrl-C and SIGTERM
    take effect once the file is in place (`interrupts_deferred`)."""
    with interrupts_deferred(), replacing(path, tmp_name) as tmp, open(tmp, "wb") as f:
        write(f)
        f.flush()
        os.fsync(f.fileno())


@contextlib.contextmanager
def interrupts_deferred() -> Iterator[None]:
    """SIGINT and SIGTERM received inside wait for its end, then act as they would have. An
    interrupt raised inside a writer (torch's zip writer) made it fail with an error of its own
    instead, and the clean stop became a traceback. Only the main thread handles signals."""
    wanted = (signal.SIGINT, signal.SIGTERM)  # delivered in this order: SIGTERM's exception, last, wins
    previous = {s: signal.getsignal(s) for s in wanted}
    if threading.current_thread() is not threading.main_thread() or None in previous.values():
        yield  # None: a handler not set from Python, which could not be put back
        return
    pending: list[int] = []

    def hold(signum: int, frame: object) -> None:
        if not pending:  # a large checkpoint takes a while: say why the stop waits
            print("relayrl: stopping once the file being written is complete", file=sys.stderr, flush=True)
        pending.append(signum)

    try:
        with _blocked(wanted):  # no signal lands between two handler swaps
            for sig in wanted:
                signal.signal(sig, hold)
        yield
    finally:
        with _blocked(wanted):
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        _deliver([sig for sig in wanted if sig in pending], previous)


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


@contextlib.contextmanager
def _blocked(signals: tuple[int, ...]) -> Iterator[None]:
    """`signals` held back by the OS while inside (POSIX); elsewhere nothing is held."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, signals)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def write_text(path: Path, text: str) -> None:
    write_with(path, lambda f: f.write(text.encode()))


def torch_save(obj: Any, path: Path, tmp_name: str | None = None) -> None:
    import torch

    write_with(path, lambda f: torch.save(obj, f), tmp_name)


def _fsync_folder(folder: Path) -> None:
    with contextlib.suppress(OSError):  # some filesystems cannot open a folder for fsync
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
