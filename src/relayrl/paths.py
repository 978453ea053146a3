"""Where `plot`, `video` and `export` write: a file the user names (`--out`), its folder created."""

from __future__ import annotations

from pathlib import Path

from relayrl.errors import UserError


def output_path(out: str | Path | None, default: Path) -> Path:
    """`out` (or `default`) with its parent folder created; one-line UserError where it cannot be."""
    path = Path(out) if out else default
    if path.is_dir():
        raise UserError(f"--out {str(path)!r} is a folder; give a file name in it")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UserError(f"cannot create the folder of --out {str(path)!r}: {e.strerror or e}") from None
    return path
