"""Files written atomically: a reader, or a run that crashes mid-write, sees the old file or the
new one, never a partial file, and a failed write leaves no temp file behind."""

from __future__ import annotations

import contextlib
import os
import signal
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
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    if threading.current_thread() is not threading.main_thread() or None in previous.values():
        yield  # None: a handler not set from Python, which could not be put back
        return
    pending: list[int] = []
    for s in previous:
        signal.signal(s, lambda signum, frame: pending.append(signum))
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        for s in dict.fromkeys(pending):
            handler = previous[s]
            if callable(handler):
                handler(s, None)
            elif handler == signal.SIG_DFL:
                signal.raise_signal(s)


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
