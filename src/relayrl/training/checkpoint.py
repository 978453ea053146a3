"""Checkpoints as plain dicts, written atomically; the previous one is kept until the new one
is complete, and a corrupt newest checkpoint falls back to the one before it."""

from __future__ import annotations

import os
import re
import warnings
from pathlib import Path
from typing import Any

import torch

from relayrl.errors import CheckpointError

_NAME = re.compile(r"^ckpt-(\d{12})\.pt$")


def atomic_torch_save(obj: Any, path: Path) -> None:
    """Write to a temp file in the same folder, fsync, rename over `path`, fsync the folder.

    A crash at any moment leaves either the old file or the new one, never a partial file.
    """
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        torch.save(obj, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def list_checkpoints(folder: Path) -> list[Path]:
    """Complete checkpoints, oldest first."""
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if _NAME.match(p.name))


def save_checkpoint(folder: Path, env_steps: int, state: dict[str, Any], keep: int = 2) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"ckpt-{env_steps:012d}.pt"
    atomic_torch_save(state, path)
    for old in list_checkpoints(folder)[:-keep]:
        old.unlink(missing_ok=True)
    for partial in folder.glob("ckpt-*.pt.tmp"):  # left by writes that a kill interrupted
        partial.unlink(missing_ok=True)
    return path


def load_latest_checkpoint(folder: Path) -> dict[str, Any]:
    """The newest readable checkpoint; a corrupt one is reported and the one before it used."""
    candidates = list_checkpoints(folder)
    if not candidates:
        raise CheckpointError(f"no checkpoint in {folder} (nothing to resume from)")
    for path in reversed(candidates):
        try:
            return torch.load(path, map_location="cpu", weights_only=False)
        except Exception as e:  # a truncated or corrupt file: fall back to an older one
            warnings.warn(f"checkpoint {path} is unreadable ({type(e).__name__}: {e}); trying an older one",
                          stacklevel=2)
    raise CheckpointError(f"every checkpoint in {folder} is unreadable")
