"""Output whose reader has gone does not stop the work: `relayrl train ... | head -3` (the reader
closes), `... | tee log` stopped by Ctrl-C (the terminal's SIGINT ends tee too), a closed
terminal. A write then fails with EPIPE or EIO, and a run would die at its next progress line,
before the checkpoint a stop writes. `pipe_safe` points such a stream's file descriptor at
/dev/null at the first failure and goes on: no one can read those lines any more. Text its
encoding cannot spell (a run directory's name in another script, redirected on Windows) is
written escaped, as Python writes it to stderr, not raised after the work is done."""

from __future__ import annotations

import contextlib
import errno
import os
import sys
from collections.abc import Iterator
from typing import Any, TextIO

_GONE = (errno.EPIPE, errno.EIO)


class PipeSafe:
    """`stream` (sys.stdout or sys.stderr) with writes that outlive its reader."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream

    def write(self, text: str) -> int:
        try:
            return self.stream.write(text)
        except OSError as e:
            self._drop_reader(e)
            return self.stream.write(text)
        except UnicodeEncodeError:  # a path the stream's code page cannot spell (Windows' cp1252, redirected)
            encoding = self.stream.encoding or "utf-8"
            return self.stream.write(text.encode(encoding, "backslashreplace").decode(encoding))

    def flush(self) -> None:
        try:
            self.stream.flush()
        except OSError as e:
            self._drop_reader(e)
            self.stream.flush()

    def _drop_reader(self, error: OSError) -> None:
        if error.errno not in _GONE:
            raise error
        to_devnull(self.stream.fileno())  # the buffered lines go there too, at the retry

    def __getattr__(self, name: str) -> Any:  # isatty, fileno, encoding, ...: the stream's own
        return getattr(self.stream, name)


def to_devnull(fd: int) -> None:
    """File descriptor `fd` pointed at /dev/null: what is written to it from now on goes nowhere."""
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, fd)
    finally:
        os.close(null)


@contextlib.contextmanager
def pipe_safe() -> Iterator[None]:
    """sys.stdout and sys.stderr as `PipeSafe` streams inside, put back after."""
    out, err = sys.stdout, sys.stderr
    # None: the descriptor was closed at start (`>&-`, a daemon), where print() writes nothing
    safe = [None if s is None else PipeSafe(s) for s in (out, err)]
    sys.stdout, sys.stderr = safe  # type: ignore[assignment]
    try:
        yield
    finally:
        for stream in safe:  # what is buffered for a pipe goes now, not at exit where no one catches EPIPE
            with contextlib.suppress(OSError, ValueError):  # ValueError: a stream the work closed
                if stream is not None:
                    stream.flush()
        sys.stdout, sys.stderr = out, err
