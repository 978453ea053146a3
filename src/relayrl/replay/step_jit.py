"""B envs, one staged step, no episode end: a TransitionWriter's flush in two compiled loops.

A batched 1:1 collect/train loop (sac-batched: 32 envs, a gradient step after every batched
step) flushes its writer after every step. The general path (`_Writer._flush_one`) spends
~60 NumPy calls on 32-element arrays there (~170 us before the table insert); these loops
write the same rows and close the same items in ~10 us. Like the compiled sum tree they
need numba (`relayrl[fast]`); without it, or with RELAYRL_NUMBA=0, the NumPy path runs.
tests/test_replay_writers.py checks that both give the same store, items and table.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING

import numpy as np

from relayrl.replay.storage import to_numpy
from relayrl.replay.sumtree_jit import _compile
from relayrl.types import Transition

if TYPE_CHECKING:
    from relayrl.replay.writers import TransitionWriter


@_compile
def _evictable(stamp: np.ndarray, item_key: np.ndarray, slot_key: np.ndarray, head: np.ndarray, rows: int,
               k: int, out: np.ndarray) -> int:
    """StepStore.evictable + _Writer._evict's liveness filter for each env's next row: the
    keys still in the table of items that writing row `head` would corrupt. Returns their count."""
    n = 0
    size = slot_key.size
    for b in range(head.size):
        p = head[b] - rows + k - 1  # the newest item that reads the row about to be reused
        if p < 0:
            continue
        i = b * rows + p % rows
        if stamp[i] == p + 1:
            key = item_key[i]
            if key >= 0 and slot_key[key % size] == key:
                out[n] = key
                n += 1
    return n


@_compile
def _write_and_close(frame: np.ndarray, action: np.ndarray, reward: np.ndarray, stamp: np.ndarray,
                     start: np.ndarray, last: np.ndarray, terminated: np.ndarray, item_key: np.ndarray,
                     ret: np.ndarray, disc: np.ndarray, nlen: np.ndarray, head: np.ndarray, ep_start: np.ndarray,
                     open_from: np.ndarray, rows: int, n: int, powers: np.ndarray, obs: np.ndarray,
                     act: np.ndarray, rew: np.ndarray, items: np.ndarray) -> int:
    """StepStore.write_step + TransitionWriter._close_newest + the rows of `_insert`: write
    one row per env, then close the item n rows back where it is in the open episode.
    `items[:m]` gets (ref, row, next row) per closed item, in ref order (as `_insert` sorts
    them, so FIFO removal follows time); returns m."""
    num_envs = head.size
    for b in range(num_envs):
        pos = head[b]
        i = b * rows + pos % rows
        frame[i, :] = obs[b, :]
        action[i, :] = act[b, :]
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
        order = np.argsort(items[:m, 0])
        items[:m] = items[:m][order]
    return m


@_compile
def write_records(slot_ref: np.ndarray, slot_rows: np.ndarray, slots: np.ndarray, items: np.ndarray,
                  ret: np.ndarray, disc: np.ndarray) -> None:
    """`_Writer.write` for a batch of items: each slot's ref and its record (row, next row, and
    the row's return and discount). ~2 us for 32 items where the NumPy path's record
    building takes ~11 us (2026-11-23)."""
    for j in range(slots.size):
        slot = slots[j]
        row = items[j, 1]
        slot_ref[slot] = items[j, 0]
        rec = slot_rows[slot]
        rec["row"] = row
        rec["next"] = items[j, 2]
        rec["ret"] = ret[row]
        rec["disc"] = disc[row]


def bind_batched_step(w: TransitionWriter) -> Callable[[TransitionWriter, Transition], None]:
    """`batched_step` for writer `w`, with its columns bound once (when the writer is built)."""
    return partial(batched_step, columns=_flat_columns(w))


def _flat_columns(w: TransitionWriter) -> tuple[np.ndarray, ...]:
    """The writer's flat columns as the loops take them: plain 2-D/1-D ndarrays (views, memmap
    columns too), in `_write_and_close`'s order. Frames and actions on a torch device are
    written apart (`batched_step`): the loops get empty rows for them."""
    if w.store.on_device:
        frame = action = np.empty((w.store.B * w.store.T, 0), np.float32)
    else:
        frame, action = np.asarray(w._frame), np.asarray(w._action)
    return (frame.reshape(frame.shape[0], -1), action.reshape(action.shape[0], -1),
            *(np.asarray(c) for c in (w._reward, w._stamp, w._start, w._last, w._terminated, w._item_key,
                                      w._ret, w._disc, w._nlen)))


def batched_step(w: TransitionWriter, t: Transition, columns: tuple[np.ndarray, ...]) -> None:
    """Append step `t` of a B-env TransitionWriter in which no episode ended, and insert the
    items it closes: `_Writer._flush_one`'s NumPy path, compiled. `columns`: `_flat_columns(w)`."""
    s, table = w.store, w.table
    b = s.B
    stamp, item_key = columns[3], columns[7]
    evict = np.empty(b, np.int64)
    count = _evictable(stamp, item_key, table.slot_key, s.head, s.T, s.k, evict)
    if count:
        table.delete(evict[:count])
    frames = t.obs[:, -1] if s.k > 1 else t.obs
    items = np.empty((b, 3), np.int64)
    if s.on_device:  # the rows this step takes; the loops write the bookkeeping, torch the data
        rows = s.head_rows()
        s._put("frame", rows, frames)
        s._put("action", rows, t.action)
        frames_np = actions_np = np.empty((b, 0), np.float32)
    else:
        frames_np = np.ascontiguousarray(to_numpy(frames)).reshape(b, -1)
        actions_np = np.ascontiguousarray(to_numpy(t.action)).reshape(b, -1)
    m = _write_and_close(*columns, s.head, s.ep_start, w._open_from, s.T, w.n, w.powers, frames_np, actions_np,
                         np.ascontiguousarray(to_numpy(t.reward)).reshape(b), items)
    if m:
        item_key[items[:m, 1]] = table.insert_batch(items[:m], n=m)
