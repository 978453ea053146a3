"""A writer's items as a Table's storage: references into a StepStore.

A writer appends steps to a StepStore and inserts items that name rows of it; the Table
holds this storage and calls `write` with the slots it gave those items and `read` with the
slots it sampled. An item is a row of three int64s: (position * B + env, flat row, flat row
of its next observation). Per slot the storage keeps that reference and a record of what a
read needs before the frames (`SLOT_RECORD`), so a sampled item costs one gather there.

`TransitionStorage` reads n-step transitions (a `Batch`), `SequenceStorage` sequences of
rows (a `SequenceBatch`). The per-env episode state a checkpoint needs to continue open
episodes (`open_from`) lives here too, beside the rows it indexes.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import torch

from relayrl.compile import numba_available
from relayrl.replay.steps import StepStore
from relayrl.types import Batch

# A slot's record: the item's flat row, its next observation's row, and (transition items)
# its n-step return and discount, copied from the rows when the item is inserted: one
# 24-byte record per sampled item instead of four scattered reads.
SLOT_RECORD = np.dtype([("row", np.int64), ("next", np.int64), ("ret", np.float32), ("disc", np.float32)])


class SequenceBatch(NamedTuple):
    """Sampled sequences, [N, L, ...]. Where `last` is set the row is a final observation
    and its action and reward are padding."""

    obs: torch.Tensor  # [N, L, *obs_shape]
    action: torch.Tensor  # [N, L, *act_shape]
    reward: torch.Tensor  # [N, L]
    last: torch.Tensor  # [N, L] bool
    terminated: torch.Tensor  # [N, L] bool, on last rows: the episode terminated (vs truncated)


class StepStorage:
    """The Table's storage for items made of StepStore rows (see the module docstring).
    `fast`: write several items' records in a compiled loop when numba is there."""

    def __init__(self, store: StepStore, capacity: int, pin_memory: bool = False, fast: bool = True) -> None:
        self.store = store
        self.num_envs, self.rows = store.B, store.T
        self.pin_memory = pin_memory
        self.slot_ref = np.zeros(capacity, dtype=np.int64)  # slot -> pos * B + env
        self.slot_rows = np.zeros(capacity, dtype=SLOT_RECORD)
        self.open_from = np.zeros(store.B, dtype=np.int64)  # per env: first position that may still become an item
        self.saved_episodes: tuple[Any, Any] = (None, None)  # (open_from, ep_start) of a loaded checkpoint
        self._ret, self._disc, self._nlen = store.flat("ret"), store.flat("disc"), store.flat("nlen")
        self._item_key = store.flat("item_key")
        self.bind(np.full(capacity, -1, dtype=np.int64))  # until the table hands over its key map
        self._write_records: Any = None  # the NumPy path
        if fast and numba_available():
            from relayrl.replay.step_storage_fast import write_records
            self._write_records = write_records

    def bind(self, slot_key: np.ndarray) -> None:
        """The table's key map (slot -> live key, -1: empty), read to tell live items apart."""
        self.slot_key = slot_key
        # What `write_records` reads and writes besides the slot map, as plain ndarray views.
        self._columns = (np.asarray(self._ret), np.asarray(self._disc), slot_key, np.asarray(self._item_key))

    def share_slot_map(self, other: StepStorage) -> None:
        """Use `other`'s slot map: storages of one table (a WriterGroup's) own disjoint slots."""
        self.slot_ref, self.slot_rows = other.slot_ref, other.slot_rows

    # ---- the Table's storage interface ---------------------------------------------------
    def write(self, slots: np.ndarray, items: np.ndarray) -> None:
        """items: [n, 3] rows of (pos * B + env, flat row, flat next row). Each item's row also
        notes the item's key (`item_key`, from the table's key map): the item to evict when the
        row is reused."""
        if len(slots) == 1:
            slot, (ref, row, nxt) = slots[0], items[0].tolist()
            self.slot_ref[slot] = ref
            self.slot_rows[slot] = (row, nxt, self._ret[row], self._disc[row])
            self._item_key[row] = self.slot_key[slot]
            return
        if self._write_records is not None:
            self._write_records(self.slot_ref, self.slot_rows, slots, items, *self._columns)
            return
        self.slot_ref[slots] = items[:, 0]
        self.slot_rows[slots] = self._records(items[:, 1], items[:, 2])
        self._item_key[items[:, 1]] = self.slot_key.take(slots)

    def read(self, slots: np.ndarray) -> Any:
        raise NotImplementedError

    def stale(self, slots: np.ndarray) -> np.ndarray:
        """Which items' rows no longer hold what they were written from (memmap files reopened)."""
        envs, pos = self.refs(slots)
        return ~self.store.valid(envs, pos, self.ahead(envs, pos))

    def state_dict(self) -> dict[str, Any]:
        return {"store": self.store.state_dict(), "slot_ref": self.slot_ref.copy(), "open_from": self.open_from.copy()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.store.load_state_dict(state["store"])
        self.slot_ref[:] = state["slot_ref"]
        self.refresh_slot_rows()
        self.open_from[:] = self.store.head  # resumed actors start new episodes, unless
        self.saved_episodes = (state.get("open_from"), state["store"].get("ep_start"))  # they continue them

    # ---- for readers and writers ---------------------------------------------------------
    def refs(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Env and position of the items in `slots`."""
        ref = self.slot_ref.take(slots)
        return ref % self.num_envs, ref // self.num_envs

    def ahead(self, envs: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """Rows after an item's first row that it reads."""
        raise NotImplementedError

    def next_pos(self, envs: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """Position of the row an item reads as its next observation (the row itself by default)."""
        return pos

    def refresh_slot_rows(self, slots: np.ndarray | None = None) -> None:
        """Recompute the records of `slots` (default: all) from `slot_ref`."""
        ref = self.slot_ref if slots is None else self.slot_ref[slots]
        envs, pos = ref % self.num_envs, ref // self.num_envs
        at = slice(None) if slots is None else slots
        self.slot_rows[at] = self._records(envs * self.rows + pos % self.rows,
                                           envs * self.rows + self.next_pos(envs, pos) % self.rows)

    def saved_episodes_intact(self) -> bool:
        """After `load_state_dict`: whether the rows of the episodes open at the checkpoint still
        hold what it saw (memmap files reopened after the run went on may not)."""
        open_from, _ = self.saved_episodes
        if open_from is None:
            return False
        s = self.store
        for env, first in enumerate(np.asarray(open_from, dtype=np.int64).tolist()):
            pos = np.arange(max(first - s.k + 1, 0), int(s.head[env]))  # open rows and their stacking look-back
            if pos.size and not (s.stamp[env, pos % s.T] == pos + 1).all():
                return False
        return True

    def _records(self, rows: np.ndarray, nxt: np.ndarray) -> np.ndarray:
        """Records of items at flat `rows` whose next observations are at `nxt`. An item's
        return and discount are final when it is inserted (its window has closed) and stay so
        until its row is reused, which evicts it first."""
        rec = np.empty(len(rows), SLOT_RECORD)
        rec["row"], rec["next"] = rows, nxt
        rec["ret"], rec["disc"] = self._ret.take(rows), self._disc.take(rows)
        return rec

    def _tensor(self, x: np.ndarray | torch.Tensor) -> torch.Tensor:
        if isinstance(x, torch.Tensor):  # gathered on the store's device
            return x
        t = torch.from_numpy(x)  # gathers are fresh contiguous arrays
        if self.store.on_device:  # the small host columns join the data on its device
            return t.to(self.store.device, non_blocking=True)
        return t.pin_memory() if self.pin_memory else t


class TransitionStorage(StepStorage):
    """n-step transitions; `read` returns a `Batch` (weights None: the learner sets them)."""

    def ahead(self, envs: np.ndarray, pos: np.ndarray) -> np.ndarray:
        return self.store.nlen[envs, pos % self.rows].astype(np.int64)

    def next_pos(self, envs: np.ndarray, pos: np.ndarray) -> np.ndarray:
        return pos + self.store.nlen[envs, pos % self.rows]

    def read(self, slots: np.ndarray) -> Batch:
        s = self.store
        rec = self.slot_rows.take(slots)  # one gather: rows, return and discount of each item
        i = rec["row"]
        if s.k == 1:
            obs, next_obs = s.gather("frame", i), s.gather("frame", rec["next"])
        else:
            envs, pos = self.refs(slots)
            start = s.flat("start").take(i)
            obs = s.stacks(envs, pos, start)
            next_obs = s.stacks(envs, pos + self._nlen.take(i), start)
        t = self._tensor
        # ret and disc made contiguous: as views of the records they would pickle (Ray) and pin
        # the whole record array.
        return Batch(t(obs), t(s.gather("action", i)), t(np.ascontiguousarray(rec["ret"])), t(next_obs),
                     t(np.ascontiguousarray(rec["disc"])), None)


class SequenceStorage(StepStorage):
    """Sequences of `length` rows of one episode; `read` returns a `SequenceBatch`."""

    def __init__(self, store: StepStore, capacity: int, length: int, pin_memory: bool = False,
                 fast: bool = True) -> None:
        super().__init__(store, capacity, pin_memory, fast)
        self.length = length

    def ahead(self, envs: np.ndarray, pos: np.ndarray) -> np.ndarray:
        return np.full(len(pos), self.length - 1, dtype=np.int64)

    def read(self, slots: np.ndarray) -> SequenceBatch:
        s, T = self.store, self.rows
        envs, pos = self.refs(slots)
        steps = pos[:, None] + np.arange(self.length)  # [N, L]
        rows = steps % T
        e = envs[:, None]
        start = s.start[envs, pos % T]
        if s.k == 1:
            obs = s.gather("frame", e * T + rows)  # [N, L, *obs]
        else:
            stacks = [s.stacks(envs, steps[:, j], start) for j in range(self.length)]
            obs = torch.stack(stacks, 1) if s.on_device else np.stack(stacks, axis=1)  # type: ignore[arg-type]
        t = self._tensor
        return SequenceBatch(t(obs), t(s.gather("action", e * T + rows)), t(s.reward[e, rows]), t(s.last[e, rows]),
                             t(s.terminated[e, rows]))
