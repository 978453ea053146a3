"""Progress lines without a terminal (a log file, a batch job): a daemon thread prints a line
every `interval_s`, so the training loop does no work for it."""

from __future__ import annotations

import threading
from collections.abc import Callable


class ProgressLines:
    interval_s = 30.0  # at least one line this often (tests shorten it)

    def __init__(self, line: Callable[[], str], log: Callable[[str], None]) -> None:
        self.line, self.log = line, log
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="relayrl-progress", daemon=True)

    def start(self) -> ProgressLines:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            try:
                self.log(self.line())
            except Exception:  # a line that cannot be made this time (a run being torn down) is skipped
                continue
