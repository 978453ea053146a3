"""Checkpoints as plain dicts, written atomically; the previous one is kept until the new one
is complete, and a corrupt newest checkpoint falls back to the one before it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from relayrl import atomic, interrupts
from relayrl.console import say
from relayrl.errors import CheckpointError
from relayrl.training.run_dir import list_checkpoints

NO_REPLAY = ("the checkpoint has no replay contents (train.checkpoint_replay = false): the replay refills from the "
             "resumed policy before learning continues")


def replay_lost(items: int, new_episodes: bool = False) -> str:
    """The line for a memmap replay whose files went on past the checkpoint resumed from (a run
    killed after more steps were written; a Ctrl-C or SIGTERM checkpoints as it stops): the
    items whose rows were overwritten are gone and, where the open episodes' rows were too, the
    envs start new episodes."""
    gone = [f"{items:,} replay items it held are gone"] * (items > 0) + ["the envs start new episodes"] * new_episodes
    return (f"the replay files were written after this checkpoint: {' and '.join(gone)}, so this resume is not bit "
            "for bit the uninterrupted run")


def save_checkpoint(folder: Path, env_steps: int, state: dict[str, Any], keep: int = 2) -> Path:
    """Write `state` as `folder/ckpt-<env steps>.pt` atomically, keeping the newest `keep` (0: all)."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"ckpt-{env_steps:012d}.pt"
    with interrupts.deferred():  # Ctrl-C waits for the pruning too: `keep` files stay
        atomic.torch_save(state, path)  # the temp name (ckpt-*.pt.tmp) never matches a checkpoint's
        for old in list_checkpoints(folder)[:-keep] if keep else []:
            old.unlink(missing_ok=True)
        for partial in folder.glob("ckpt-*.pt.tmp"):  # left by writes that a kill interrupted
            partial.unlink(missing_ok=True)
    return path


def load_latest_checkpoint(folder: Path) -> dict[str, Any]:
    """The newest readable checkpoint; a corrupt one is reported and the one before it used."""
    candidates = list_checkpoints(folder)
    if not candidates:
        raise CheckpointError(f"no checkpoint in {folder} (nothing to resume from): start the run again without "
                              "--resume (in Python: resume=False); a run that trained past step 0 needs --overwrite "
                              "(overwrite=True)")
    for n, path in enumerate(reversed(candidates)):
        try:
            bad = atomic.damaged(path)
            if bad:
                raise ValueError(bad)
            state = torch.load(path, map_location="cpu", weights_only=False)
            if not isinstance(state, dict) or "env_steps" not in state:  # another program's file under its name
                raise ValueError(f"it holds a {type(state).__name__} that is not a relayrl checkpoint")
            return state
        except Exception as e:  # a truncated or corrupt file: fall back to an older one
            detail = (str(e).strip().splitlines() or [""])[0]
            if len(detail) > 120:  # torch's explanations run long: cut at a word
                detail = detail[:120].rsplit(" ", 1)[0] + " ..."
            then = "trying an older one" if n + 1 < len(candidates) else "no older one is left"
            say(f"relayrl: checkpoint {path} is unreadable ({type(e).__name__}: {detail}); {then}")
    raise CheckpointError(f"every checkpoint in {folder} is unreadable: start the run again with --overwrite "
                          "(in Python: overwrite=True)")
