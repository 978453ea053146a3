"""One Table fed by several writers: the replay server's storage.

A writer takes whole batched steps of its own envs. Actors on other machines step out of
phase with each other, so the replay server gives each one its own writer, and the Table
its own step storage (its own StepStore rows) per writer; its sampler, remover and rate
limiter then see every actor's items together, as Reverb's server does. The Table's storage
is a `StorageGroup`: steps go to the active writer's storage, and each slot remembers the
storage that owns it, which reads it.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from relayrl.replay.step_storage import StepStorage
from relayrl.replay.steps import StepChunk
from relayrl.replay.storage import Storage
from relayrl.replay.table import Table
from relayrl.replay.writers import SequenceWriter, TransitionWriter

Writer = TransitionWriter | SequenceWriter


def split_chunk(chunk: StepChunk, max_steps: int) -> list[StepChunk]:
    """Cut a chunk into pieces of at most `max_steps` batched steps (finals follow their steps)."""
    c = chunk.done.shape[0]
    if c <= max_steps:
        return [chunk]
    pieces = []
    f = 0
    for a in range(0, c, max_steps):
        b = min(a + max_steps, c)
        nf = int(np.count_nonzero(chunk.done[a:b]))
        pieces.append(StepChunk(chunk.frames[a:b], chunk.actions[a:b], chunk.rewards[a:b], chunk.done[a:b],
                                chunk.terminated[a:b], chunk.finals[f:f + nf]))
        f += nf
    return pieces


class StorageGroup(Storage):
    """See the module docstring. Each slot belongs to one storage at a time, so the storages
    share one slot map (saved once)."""

    def __init__(self, storages: list[StepStorage], capacity: int) -> None:
        self.storages = storages
        for st in storages[1:]:
            st.slot_ref, st.slot_rows = storages[0].slot_ref, storages[0].slot_rows
        self.owner = np.zeros(capacity, dtype=np.int32)  # slot -> storage
        self.active = 0

    def bind(self, slot_key: np.ndarray) -> None:
        for st in self.storages:
            st.bind(slot_key)

    @property
    def appending(self) -> StepStorage:
        return self.storages[self.active]

    def write(self, slots: np.ndarray, items: np.ndarray) -> None:
        self.owner[slots] = self.active
        self.storages[self.active].write(slots, items)

    def _groups(self, slots: np.ndarray) -> list[tuple[int, np.ndarray]]:
        owner = self.owner.take(slots)
        first = int(owner[0]) if len(owner) else 0
        if not len(owner) or (owner == first).all():
            return [(first, np.arange(len(slots)))]
        return [(int(w), np.flatnonzero(owner == w)) for w in np.unique(owner)]

    def read(self, slots: np.ndarray) -> Any:
        groups = self._groups(slots)
        if len(groups) == 1:
            return self.storages[groups[0][0]].read(slots)
        parts = [self.storages[w].read(slots[idx]) for w, idx in groups]
        inverse = torch.from_numpy(np.argsort(np.concatenate([idx for _, idx in groups]), kind="stable"))
        fields = [None if f[0] is None else torch.cat(f).index_select(0, inverse) for f in zip(*parts, strict=True)]
        return type(parts[0])(*fields)

    def stale(self, slots: np.ndarray) -> np.ndarray:
        out = np.zeros(len(slots), dtype=bool)
        for w, idx in self._groups(slots):
            out[idx] = self.storages[w].stale(slots[idx])
        return out

    def state_dict(self) -> dict[str, Any]:
        states = [st.state_dict() for st in self.storages]
        slot_ref = states[0]["slot_ref"]
        for state in states:
            del state["slot_ref"]  # the shared map, saved once
        return {"writers": states, "owner": self.owner.copy(), "slot_ref": slot_ref}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if len(state["writers"]) != len(self.storages):
            raise ValueError(f"the saved replay has {len(state['writers'])} writers (actors), this one "
                             f"{len(self.storages)}")
        self.owner[:] = state["owner"]
        for st, saved in zip(self.storages, state["writers"], strict=True):
            st.load_state_dict({**saved, "slot_ref": state["slot_ref"]})  # resumed actors start new episodes
        # Each load rewrote the whole shared map with its own n-step lengths; each storage's
        # own slots read its own store.
        for i, st in enumerate(self.storages):
            st.refresh_slot_rows(np.flatnonzero(self.owner == i))


class WriterGroup:
    """`make_writer(table, index, path)` builds writer `index`; every writer inserts into `table`.

    `write_chunk(index, chunk)` is thread-safe (one chunk at a time: a chunk's inserts may
    block on the rate limiter, and the next actor's chunk waits behind it, as it would for
    the limiter anyway). Reads and inserts meet only under the Table's own lock.
    """

    def __init__(self, table: Table, num_writers: int,
                 make_writer: Callable[[Table, int, Path | None], Writer], path: str | Path | None = None) -> None:
        if num_writers < 1:
            raise ValueError(f"num_writers={num_writers} is not valid; it must be >= 1")
        self.table = table
        root = Path(path) if path is not None else None
        self.writers: list[Writer] = []
        storages: list[StepStorage] = []
        for i in range(num_writers):
            self.writers.append(make_writer(table, i, None if root is None else root / f"writer{i}"))
            storage = table.storage  # the step storage writer i just gave the table
            assert isinstance(storage, StepStorage)
            storages.append(storage)
        self.storage = StorageGroup(storages, table.max_size)
        table.set_storage(self.storage)  # the table keeps every writer's steps; the group routes
        self._lock = threading.Lock()

    def write_chunk(self, index: int, chunk: StepChunk) -> None:
        writer = self.writers[index]
        with self._lock:
            self.storage.active = index
            for piece in split_chunk(chunk, writer.max_staged):  # rows reused mid-chunk would corrupt it
                writer.write_chunk(piece)

    def restart_episodes(self, index: int) -> None:
        """Writer `index` forgets its open episodes (its actor died and was restarted)."""
        with self._lock:
            self.storage.active = index
            self.writers[index].restart_episodes()
