"""Where `plot`, `video` and `export` write: a file the user names (`--out`), its folder created;
and the name a run's checkpoints have."""

from __future__ import annotations

import contextlib
import os
import re
import tempfile
from collections.abc import Iterator
from pathlib import Path

from relayrl.errors import UserError

# RUN_DIR/checkpoints/ckpt-<env steps, 12 digits>.pt (the temp name of one being written never matches)
CHECKPOINT_NAME = re.compile(r"^ckpt-(\d{12})\.pt$")


def is_folder(out: str | Path) -> bool:
    """Whether an --out names a folder: one that exists, or a name ending in a slash."""
    return user_path(out).is_dir() or str(out).endswith(("/", os.sep))


def user_path(path: str | os.PathLike[str]) -> Path:
    """A path a caller gives (a run directory, a policy file, --out), "~" expanded as a shell
    would have done on the command line."""
    return Path(path).expanduser()


def existing_ancestor(path: Path) -> Path:
    """`path` (made absolute) or the nearest of its parent folders that exists: where a folder
    still to be made would go, for its permission or its disk's free space."""
    existing = path.absolute()
    while not existing.exists() and existing.parent != existing:
        existing = existing.parent
    return existing


def output_path(out: str | Path | None, default: Path) -> Path:
    """`out` (or `default`) with its parent folder created; one-line UserError where it cannot be
    (a file in the way, a folder that is not writable, no file extension), before any work is
    done. A folder (one that exists, or a name ending in a slash) gets `default`'s file name in it."""
    path = user_path(out) if out else default
    if out and is_folder(out):
        path = path / default.name
    if not path.suffix:
        raise UserError(f"--out {str(out)!r} has no file extension; give a file name such as "
                        f"{path.name}{default.suffix}, or a folder ending in /")
    name = f"--out {str(path)!r}" if out else repr(str(path))
    where = "" if out else "; give --out PATH somewhere writable"
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UserError(f"cannot create the folder of {name}: {e.strerror or e}{where}") from None
    if not os.access(path.parent, os.W_OK):
        raise UserError(f"cannot write {name}: its folder is not writable{where}")
    try:  # what access() cannot tell (root in /proc, a read-only mount): a file made there and taken out
        with tempfile.NamedTemporaryFile(dir=path.parent, prefix=".relayrl-check-"):
            pass
    except OSError as e:
        raise UserError(f"cannot write {name}: {e.strerror or e}{where}") from None
    return path


@contextlib.contextmanager
def writing(path: Path) -> Iterator[None]:
    """An OSError while writing `path` (permission, a full disk) as one line, not a traceback."""
    try:
        yield
    except OSError as e:
        raise UserError(f"cannot write {str(path)!r}: {e.strerror or e}") from None
