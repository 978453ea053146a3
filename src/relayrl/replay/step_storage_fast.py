"""Compiled twins (numba, the `relayrl[fast]` extra) of a StepStorage's hot paths.

- `write_records`: `StepStorage.write` of several items in one loop. The NumPy path builds
  the records with a handful of array calls, whose fixed costs are most of a 32-item insert.
- `OneStep`: a TransitionStorage's `one_step`: `evictions` and `append` of one batched step
  without episode ends. A 1:1 collect/train loop appends after every batched step; the
  general path (`evictions`, `append`) spends dozens of NumPy calls on [B] arrays there,
  whose fixed costs are the whole bill at small B. These loops write the same rows and close
  the same items; the table then deletes and inserts them as on the general path.

Without numba, with RELAYRL_NUMBA=0, or with `fast=False` the NumPy paths run;
tests/test_replay_writers.py checks that both leave the same store, items and table.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from relayrl.arrays import to_numpy
from relayrl.compile import njit

if TYPE_CHECKING:
    from relayrl.replay.step_storage import TransitionStorage

@njit
def write_records(slot_ref: np.ndarray, slot_rows: np.ndarray, slots: np.ndarray, items: np.ndarray,
                  ret: np.ndarray, disc: np.ndarray, slot_key: np.ndarray, item_key: np.ndarray) -> None:
    for j in range(slots.size):
        slot = slots[j]
        row = items[j, 1]
        slot_ref[slot] = items[j, 0]
        rec = slot_rows[slot]
        rec["row"] = row
        rec["next"] = items[j, 2]
        rec["ret"] = ret[row]
        rec["disc"] = disc[row]
        item_key[row] = slot_key[slot]


@njit
def evictable(stamp: np.ndarray, item_key: np.ndarray, slot_key: np.ndarray, head: np.ndarray, rows: int, k: int,
              out: np.ndarray) -> int:
    """StepStore.evictable for each env's next row, live items only: the keys of the items still
    in the table (`slot_key`, the table's key map) that writing row `head` would corrupt, into
    `out`; returns their count. Most such items are long gone (the remover took them first)."""
    n = 0
    for b in range(head.size):
        p = head[b] - rows + k - 1  # the newest item that reads the row about to be reused
        if p < 0:
            continue
        i = b * rows + p % rows
        if stamp[i] == p + 1:
            key = item_key[i]
            if key >= 0 and slot_key[key % slot_key.size] == key:
                out[n] = key
                n += 1
    return n


@njit
def _write_and_close(frame: np.ndarray, action: np.ndarray, reward: np.ndarray, stamp: np.ndarray,
                     start: np.ndarray, last: np.ndarray, terminated: np.ndarray, item_key: np.ndarray,
                     ret: np.ndarray, disc: np.ndarray, nlen: np.ndarray, head: np.ndarray, ep_start: np.ndarray,
                     open_from: np.ndarray, rows: int, n: int, powers: np.ndarray, obs: np.ndarray,
                     act: np.ndarray, rew: np.ndarray, items: np.ndarray) -> int:
    """Write one row per env (as StepStore.write_chunk for one step without episode ends), then
    close the item n rows back where it is in the open episode (as TransitionStorage._close_items
    does then). `items[:m]` gets (ref, row, next row) per closed item, in ref order (as
    `StepStorage._items` sorts them, so FIFO removal follows time); returns m."""
    num_envs = head.size
    for b in range(num_envs):
        pos = head[b]
        i = b * rows + pos % rows
        for c in range(obs.shape[1]):  # loops, not slice copies: those cost seconds of compiling
            frame[i, c] = obs[b, c]
        for c in range(act.shape[1]):
            action[i, c] = act[b, c]
        reward[i] = rew[b]
        stamp[i] = pos + 1
        start[i] = ep_start[b]
        last[i] = False
        terminated[i] = False
        item_key[i] = -1
        head[b] = pos + 1
    m = 0
    ordered = True
    for b in range(num_envs):
        q = head[b] - 1 - n
        if q < open_from[b]:
            continue
        base = b * rows
        total = np.float64(reward[base + q % rows])
        for j in range(1, n):  # left to right, in float64, as the NumPy path sums
            total += reward[base + (q + j) % rows] * powers[j]
        iq = base + q % rows
        ret[iq] = total
        disc[iq] = powers[n]
        nlen[iq] = n
        open_from[b] = q + 1
        items[m, 0] = q * num_envs + b
        items[m, 1] = iq
        items[m, 2] = base + (q + n) % rows
        if m > 0 and items[m, 0] < items[m - 1, 0]:
            ordered = False
        m += 1
    if not ordered:  # envs at different positions: oldest first
        _sort_rows(items, m)
    return m


@njit
def _sort_rows(items: np.ndarray, m: int) -> None:
    """Sort items[:m] by their first column (unique refs) in place: a shell sort, which compiles
    in a fraction of the time numba's np.argsort plus a row gather takes from a cold cache
    (every new install, every CI run). The rows come nearly in order (one run per group of
    envs at the same position), where it is fastest."""
    gap = m // 2
    while gap > 0:
        for i in range(gap, m):
            r0, r1, r2 = items[i, 0], items[i, 1], items[i, 2]
            j = i
            while j >= gap and items[j - gap, 0] > r0:
                items[j, 0], items[j, 1], items[j, 2] = items[j - gap, 0], items[j - gap, 1], items[j - gap, 2]
                j -= gap
            items[j, 0], items[j, 1], items[j, 2] = r0, r1, r2
        gap //= 2


class OneStep:
    """The compiled one-step append of TransitionStorage `storage`: its columns bound once, as
    the loops take them (plain 2-D/1-D ndarrays, memmap columns too). Frames and actions of a
    store on a torch device are written by torch (`StepStore.write_data`); the loops get empty
    rows for them."""

    def __init__(self, storage: TransitionStorage) -> None:
        self.storage = storage
        s = self.store = storage.store
        if s.on_device:
            frame = action = np.empty((s.num_envs * s.rows, 0), np.float32)
        else:
            frame, action = np.asarray(s.flat("frame")), np.asarray(s.flat("action"))
        self.columns = (frame.reshape(frame.shape[0], -1), action.reshape(action.shape[0], -1),
                        *(np.asarray(s.flat(c)) for c in ("reward", "stamp", "start", "last", "terminated",
                                                           "item_key", "ret", "disc", "nlen")))
        self.items = np.empty((s.num_envs, 3), np.int64)
        self.keys = np.empty(s.num_envs, np.int64)

    def evictions(self) -> np.ndarray:
        """Keys of the live items that the next step's rows overwrite."""
        s, columns = self.store, self.columns
        count = evictable(columns[3], columns[7], self.storage.slot_key, s.head, s.rows, s.frame_stack, self.keys)
        return self.keys[:count]

    def append(self, frames: Any, actions: Any, rewards: Any) -> np.ndarray:
        """Append one step (no episode ends) and return the items it closes ([m, 3], a view
        valid until the next call)."""
        s, st, b = self.store, self.storage, self.store.num_envs
        if s.on_device:
            s.write_data(s.envs * s.rows + s.head % s.rows, frames, actions)  # the next step's rows
            frames_np = actions_np = np.empty((b, 0), np.float32)
        else:
            frames_np = np.ascontiguousarray(to_numpy(frames)).reshape(b, -1)
            actions_np = np.ascontiguousarray(to_numpy(actions)).reshape(b, -1)
        rewards_np = np.ascontiguousarray(to_numpy(rewards)).reshape(b)
        m = _write_and_close(*self.columns, s.head, s.ep_start, st.open_from, s.rows, st.n_step, st.powers,
                             frames_np, actions_np, rewards_np, self.items)
        return self.items[:m]
