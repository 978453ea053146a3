"""Files written atomically: a reader, or a run that crashes mid-write, sees the old file or the
new one, never a partial file, and a failed write leaves no temp file behind. What torch wrote
is checked against its own checksums when it is read back (`damaged`)."""

from __future__ import annotations

import contextlib
import errno
import os
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

from relayrl import interrupts
from relayrl.errors import UserError, one_line


@contextlib.contextmanager
def replacing(path: Path, tmp_name: str | None = None) -> Iterator[Path]:
    """Yields a temp path beside `path`; on success it is renamed over `path` and the folder
    synced, on failure removed. `tmp_name` for writers that want a given suffix."""
    path = Path(path)
    tmp = path.with_name(tmp_name or path.name + ".tmp")  # never matches a glob for the real suffix
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(OSError):
            tmp.unlink()
        full = _os_error(e, _FULL)  # torch's writer wraps the OSError in a RuntimeError of its own
        if full is not None:
            raise UserError(f"cannot write {str(path)!r}: {full.strerror or full} (its previous version, if any, is "
                            f"kept): {_advice(full, path.parent)}") from None
        if isinstance(e, RuntimeError) and "unexpected pos" in str(e):  # torch's writer, its bytes cut short
            raise UserError(f"cannot write {str(path)!r}: the write stopped short (torch: {str(e).strip()}; its "
                            "previous version, if any, is kept): the disk is full or a file-size limit (ulimit -f) "
                            "was reached") from None
        refused = _os_error(e, _DENIED)  # a read-only folder (or mount) inside a writable run directory
        if refused is not None:
            raise UserError(f"cannot write {str(path)!r}: {refused.strerror or refused} (its previous version, if any, "
                            f"is kept): {_advice(refused, path.parent)}") from None
        raise
    _fsync_folder(path.parent)


_FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)  # EFBIG: a file-size limit (`ulimit -f`), Python ignoring SIGXFSZ
_DENIED = (errno.EROFS, errno.EACCES, errno.EPERM)
_FULL_FIX = {errno.ENOSPC: "free some space", errno.EDQUOT: "free some space", errno.EFBIG: "raise the file-size "
             "limit (ulimit -f)"}


def unwritable(error: BaseException | None, folder: Path | None = None) -> OSError | None:
    """The OSError in the chain of `error` that a write cannot get past (no space left, a quota
    or file-size limit, a folder or mount made read-only), where there is one. With `folder`,
    a refusal counts only for a file inside it, or one unnamed (TensorBoard's writer names
    none): a user's env refused a file of its own is the env's error, with its traceback."""
    found = _os_error(error, _FULL + _DENIED)
    if found is None or folder is None or found.errno not in _DENIED or not found.filename:
        return found
    return found if Path(os.path.abspath(found.filename)).is_relative_to(os.path.abspath(folder)) else None


def unwritable_line(error: OSError, folder: Path) -> str:
    """The one line for a write into `folder` that `error` (`unwritable`'s) stopped: the file,
    where the error names one (TensorBoard's writer names none), and what to do."""
    where = f" {str(error.filename)!r}" if error.filename else f" in {str(folder)!r}"
    parent = Path(error.filename).parent if error.filename else folder
    return f"cannot write{where}: {error.strerror or error}: {_advice(error, parent)}"


def _advice(error: OSError, parent: Path) -> str:
    """What to do about a write into `parent` that `error` (full, limited or refused) stopped."""
    return _FULL_FIX.get(error.errno or 0) or f"make {str(parent)!r} writable"


def _os_error(error: BaseException | None, errnos: tuple[int, ...]) -> OSError | None:
    """The OSError with one of `errnos` in the chain of `error` and what it was raised from."""
    for _ in range(10):
        if error is None:
            break
        if isinstance(error, OSError) and error.errno in errnos:
            return error
        error = error.__cause__ or error.__context__
    return None


def write_with(path: Path, write: Callable[[IO[bytes]], Any], tmp_name: str | None = None) -> None:
    """Call `write(file)` on a temp file, fsync it, rename it over `path`. Ctrl-C and SIGTERM
    take effect once the file is in place (`interrupts.deferred`)."""
    with interrupts.deferred(), replacing(path, tmp_name) as tmp, open(tmp, "wb") as f:
        write(f)
        f.flush()
        os.fsync(f.fileno())


def write_text(path: Path, text: str) -> None:
    write_with(path, lambda f: f.write(text.encode()))


def torch_save(obj: Any, path: Path, tmp_name: str | None = None) -> None:
    import torch

    write_with(path, lambda f: torch.save(obj, f), tmp_name)


def damaged(path: Path) -> str | None:
    """What is wrong with a file torch.save wrote where its bytes changed after the write (a bit
    flipped on the disk or in a copy: torch reads such a file without a word), checked against
    the CRC-32 each of its records carries; None where every record matches. A file of torch's
    legacy format (no zip) or one written without checksums (torch's `compute_crc32` turned
    off: each stored as 0) is not checked."""
    try:
        with open(path, "rb") as f:
            if f.read(4) != b"PK\x03\x04":  # not a zip: torch.load says what it is
                return None
    except OSError:  # torch.load's own error says it
        return None
    try:
        archive = zipfile.ZipFile(path)
    except Exception:  # no directory to read (a write cut short) or one zipfile cannot parse: torch.load says it
        return None
    try:
        with archive:
            for record in archive.infolist():
                if record.CRC == 0:
                    continue
                with archive.open(record) as data:  # zipfile checks the CRC as the last bytes are read
                    while data.read(1 << 22):
                        pass
    except OSError:  # unreadable midway: torch.load's own error says it
        return None
    except Exception as e:  # zipfile's reading of a changed byte: a bad CRC, or a record's header
        return f"its bytes changed after it was written ({type(e).__name__}: {one_line(str(e), 120)})"
    return None


def _fsync_folder(folder: Path) -> None:
    with contextlib.suppress(OSError):  # some filesystems cannot open a folder for fsync
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
