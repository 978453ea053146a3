"""The run directory contract: config.toml, metrics.jsonl, tb/, checkpoints/, policy/."""

from __future__ import annotations

import json
import math
import os
import shutil
import socket
from pathlib import Path
from typing import Any

from relayrl.errors import UserError
from relayrl.paths import CHECKPOINT_NAME, existing_ancestor, user_path

try:
    import fcntl
except ImportError:  # Windows: runs are not locked against each other there
    fcntl = None  # type: ignore[assignment]


def list_checkpoints(folder: Path) -> list[Path]:
    """Complete checkpoints, oldest first. Here, not in checkpoint.py, because listing them needs no
    torch: the line printed on Ctrl-C asks for them, when torch may be half-imported (importing it
    again then raises or crashes)."""
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if CHECKPOINT_NAME.match(p.name))


def checkpoint_step(path: Path) -> int:
    """The env step a checkpoint of `list_checkpoints` resumes from, read from its name."""
    match = CHECKPOINT_NAME.match(path.name)
    assert match is not None, path
    return int(match[1])


# The longest path a run writes below its directory, less the host name TensorBoard puts in it
# (`tb/events.out.tfevents.<time>.<host>.<pid>.<n>`; checkpoints' temp names are shorter)
_LONGEST_NAME = "tb/events.out.tfevents.1234567890..4194304.99"


def _path_limit(folder: Path) -> int | None:
    """The longest path the system takes in `folder` (PATH_MAX); None where it does not say."""
    try:
        return os.pathconf(folder, "PC_PATH_MAX")
    except (AttributeError, ValueError, OSError):  # Windows has no pathconf
        return None


class RunDir:
    def __init__(self, root: str | Path) -> None:
        self.root = user_path(root)
        self.config = self.root / "config.toml"
        self.metrics = self.root / "metrics.jsonl"
        self.tb = self.root / "tb"
        self.checkpoints = self.root / "checkpoints"
        self.policy = self.root / "policy"
        self.lock_file = self.root / ".lock"  # held (flock) by the process whose run writes here
        self.history = self.root / "history.json"  # each process that trained the run (training.history)
        self._lock_fd: int | None = None

    def check_not_running(self) -> None:
        """One line when another process is running a run here now."""
        if self._lock_fd is None and self.lock_file.is_file():
            self.hold_lock()  # raises when another process holds it
            self.release_lock()

    def hold_lock(self) -> None:
        """Hold .lock until `release_lock` (or this process ends)."""
        if fcntl is None or self._lock_fd is not None:
            return
        fd = os.open(self.lock_file, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise UserError(f"a run is running in {str(self.root)!r} now (another process holds its .lock); "
                            "wait for it, stop it, or choose another --run-dir") from None
        self._lock_fd = fd

    def gone(self) -> bool:
        """Whether the run directory was deleted, or replaced by another run's, while this process
        held its lock (without one, as on Windows: whether it is missing): a run writing on would
        recreate folders in it or write into another run's."""
        if self._lock_fd is None:
            return not self.root.is_dir()
        try:
            now = os.stat(self.lock_file)
        except OSError:
            return True
        held = os.fstat(self._lock_fd)
        return (now.st_ino, now.st_dev) != (held.st_ino, held.st_dev)

    def gone_line(self) -> str | None:
        """The line for a run directory that is `gone`; None where it is not."""
        if not self.gone():
            return None
        return (f"the run directory {str(self.root)!r} was deleted (or replaced by another run's) while this run "
                "trained: nothing more is written there")

    def release_lock(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    def check_writable(self) -> None:
        """One line, before anything is built or written, where the run directory cannot be made."""
        if self.root.exists() and not self.root.is_dir():
            raise UserError(f"--run-dir {str(self.root)!r} is a file, not a directory")
        existing = existing_ancestor(self.root)
        if not existing.is_dir():
            raise UserError(f"--run-dir {str(self.root)!r}: {str(existing)!r} is a file, not a directory")
        if not os.access(existing, os.W_OK | os.X_OK):
            raise UserError(f"--run-dir {str(self.root)!r}: no permission to write in {str(existing)!r}")
        longest = len(str(self.root.absolute() / _LONGEST_NAME)) + len(socket.gethostname())
        limit = _path_limit(existing)
        if limit is not None and longest >= limit:
            raise UserError(f"--run-dir is {len(str(self.root.absolute())):,} characters long: the files a run "
                            f"writes in it (its TensorBoard log's, with this machine's name) would pass the "
                            f"system's limit of {limit:,} characters for a path; choose a shorter one")
        for path, folder in ((self.config, False), (self.metrics, False), (self.tb, True), (self.checkpoints, True),
                             (self.policy, True)):
            if path.exists() and path.is_dir() != folder:
                raise UserError(f"--run-dir {str(self.root)!r}: {path.name!r} there is a "
                                f"{'file' if folder else 'directory'}, where a run keeps its "
                                f"{'folder' if folder else 'file'} of that name: move it away, or choose another "
                                "--run-dir")
            # a read-only folder (or mount) inside a writable run directory: TensorBoard's writer thread
            # would fail on it with a traceback once the run has started
            if path.exists() and not os.access(path, os.W_OK | (os.X_OK if folder else 0)):
                raise UserError(f"--run-dir {str(self.root)!r}: no permission to write in {str(path)!r}: make it "
                                "writable, or choose another --run-dir")

    def has_checkpoint(self) -> bool:
        return bool(list_checkpoints(self.checkpoints))

    def clear(self) -> None:
        """Remove what a run writes here (a new run replaces it); other files are left alone."""
        for path in (self.config, self.metrics, self.history):
            path.unlink(missing_ok=True)
        # Not replay/: a memmap replay's files are made while the new run is built, before this
        # runs; they are rewritten as the run goes and a new table never reads an old row.
        for folder in (self.tb, self.checkpoints, self.policy):
            if folder.is_dir():
                shutil.rmtree(folder)

    def create(self) -> None:
        try:
            # checkpoints/ is made by the first checkpoint: a run that writes none (train.checkpoint_interval = 0,
            # bptt-pendulum) has no empty folder that looks like one lost
            for d in (self.root, self.tb, self.policy):
                d.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            where = f" ({e.filename})" if e.filename else ""
            raise UserError(f"--run-dir {str(self.root)!r} cannot be created: {e.strerror}{where}") from None

    @classmethod
    def of(cls, path: str | Path) -> RunDir:
        """The run directory `path` names: the directory, its policy/ folder, or a file in either
        (RUN_DIR/policy/policy.pt, RUN_DIR/config.toml)."""
        p = user_path(path)
        if p.is_file():
            p = p.parent
        if p.name == "policy" and (p.parent / "config.toml").is_file():
            p = p.parent
        return cls(p)

    def require(self) -> None:
        if self.root.is_file():
            raise UserError(f"{str(self.root)!r} is a file, not a run directory (give the run's folder)")
        if not self.root.is_dir():
            if self.root.suffix == ".pt":  # a policy file named, not a folder
                older = " (runs made before eval.keep_best have no policy/best.pt)" * (self.root.name == "best.pt")
                raise UserError(f"policy file {str(self.root)!r} does not exist{older}")
            raise UserError(f"run directory {str(self.root)!r} does not exist")
        if not self.config.is_file():
            raise UserError(f"{str(self.root)!r} is not a relayrl run directory (no config.toml)")

    def read_metrics(self) -> list[dict[str, Any]]:
        return self._metrics_lines()[0]

    def _metrics_lines(self) -> tuple[list[dict[str, Any]], int]:
        """The rows, and how many lines were not JSON (cut short by a crash or a full disk)."""
        if not self.metrics.is_file():
            return [], 0
        rows, torn = [], 0
        # bytes that are not UTF-8 spoil only their own line: it is then not JSON and is passed over
        for line in self.metrics.read_text(errors="replace").splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                torn += bool(line.strip())  # a line cut short; the rest is intact
                continue
            if isinstance(row, dict) and type(row.get("step")) is int:  # a run's rows; not a line added by hand
                rows.append(row)
        return rows, torn

    def trained_to(self, read_policy: bool = True) -> int:
        """How far the run got, as far as its files say: the later of metrics.jsonl's last
        evaluation and the saved policy's env step (0: it never trained past the start).
        `read_policy=False` leaves the policy file (read with torch) out."""
        rows = self.read_metrics()
        policy = self.policy / "policy.pt"
        saved = 0
        if read_policy and policy.is_file():
            from relayrl.policy_file import load_policy_file

            try:
                saved = int(load_policy_file(policy).get("env_steps", 0))
            except UserError:  # an unreadable policy file says nothing about how far the run got
                pass
        return max(int(rows[-1].get("step", 0)) if rows else 0, saved)

    def truncate_metrics(self, after_step: int) -> tuple[list[dict[str, Any]], int]:
        """Drop rows logged after `after_step` (a resumed run logs them again) and lines that are
        not JSON; the rows kept, and how many such lines went."""
        rows, torn = self._metrics_lines()
        rows = [r for r in rows if r.get("step", 0) <= after_step]
        tmp = self.metrics.with_suffix(".jsonl.tmp")
        tmp.write_text("".join(json.dumps(r) + "\n" for r in rows))
        tmp.replace(self.metrics)
        return rows, torn


def json_row(row: dict[str, Any]) -> dict[str, Any]:
    """A metrics row as metrics.jsonl holds it: a value that is not a finite number (a training
    return before the first episode ends: NaN) is None, JSON's null."""
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()}


class MetricsLog:
    """Appends one JSON object per evaluation to metrics.jsonl, flushed line by line."""

    def __init__(self, path: Path) -> None:
        self.file = open(path, "a", buffering=1)

    def write(self, row: dict[str, Any]) -> None:
        self.file.write(json.dumps(json_row(row)) + "\n")

    def sync(self) -> None:
        """The rows written so far on disk (fsync): a checkpoint written after this never
        outlives, on a node's crash, the rows of the evaluations before it."""
        self.file.flush()
        os.fsync(self.file.fileno())

    def close(self) -> None:
        self.file.close()


def lone_policy_file(source: Any) -> bool:
    """A path to a policy file with no run directory's config.toml around it."""
    return isinstance(source, (str, Path)) and user_path(source).is_file() and not RunDir.of(source).config.is_file()
