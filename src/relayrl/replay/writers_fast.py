"""B envs, one staged step, no episode end: a TransitionWriter's flush in compiled loops.

A batched 1:1 collect/train loop (sac-batched: 32 envs, a gradient step after every batched
step) flushes its writer after every step. The general path (`_Writer._flush_one`) spends
~60 NumPy calls on 32-element arrays there (~170 us before the table insert); these loops
write the same rows and close the same items in ~10 us. When the table is Uniform/Fifo
(`table_jit`), one call (`_step_and_insert`) also inserts them and writes the slot records:
the flush is then one compiled call and ~20 lines of Python. Like the compiled sum tree they
need numba (`relayrl[fast]`); without it, or with RELAYRL_NUMBA=0, the NumPy path runs.
tests/test_replay_writers.py checks that both give the same store, items and table."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING

import numpy as np

from relayrl.arrays import to_numpy
from relayrl.compile import njit
from relayrl.replay.table_fast import insert_slots, take_slots
from relayrl.types import Transition

if TYPE_CHECKING:
    from relayrl.replay.writers import TransitionWriter


@njit
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


@njit
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
    """Sort items[:m] by their first column (unique refs) in place: a shell sort. numba's
    np.argsort plus the row gather took ~9 s to compile from a cold cache (every new install,
    every CI run); this takes ~0.3 s, and 0.75 ms for 4,096 shuffled rows (argsort: 0.4 ms).
    The rows come nearly in order (one run per group of envs at the same position), where it
    is fastest."""
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


@njit
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


@njit
def _step_and_insert(frame: np.ndarray, action: np.ndarray, reward: np.ndarray, stamp: np.ndarray, start: np.ndarray,
                     last: np.ndarray, terminated: np.ndarray, item_key: np.ndarray, ret: np.ndarray,
                     disc: np.ndarray, nlen: np.ndarray, head: np.ndarray, ep_start: np.ndarray,
                     open_from: np.ndarray, rows: int, n: int, k: int, powers: np.ndarray, obs: np.ndarray,
                     act: np.ndarray, rew: np.ndarray, items: np.ndarray, slot_ref: np.ndarray, slot_rows: np.ndarray,
                     slot_key: np.ndarray, free: np.ndarray, num_free: int, inserted: int, priority: np.ndarray,
                     max_priority: float, times_sampled: np.ndarray, dense: np.ndarray, where: np.ndarray, size: int,
                     identity: bool, queue: np.ndarray, queue_head: int, tail: int, slots: np.ndarray,
                     keys: np.ndarray) -> tuple[int, int, bool, int]:
    """The whole one-step flush for a host store whose table is Uniform/Fifo: `_write_and_close`,
    then the table's insert (`table_jit.take_slots`: free slots, then Fifo victims;
    `table_jit.insert_slots`), the writer's slot records and each row's item key, in one call
    instead of four and their Python glue. Returns (items inserted m, of them into free slots,
    the sampler's identity flag, the Fifo queue's new head); m = -1 with nothing written when a
    live item reads a row about to be reused (the caller deletes it on the general path)."""
    if _evictable(stamp, item_key, slot_key, head, rows, k, slots) > 0:
        return -1, 0, identity, queue_head
    m = _write_and_close(frame, action, reward, stamp, start, last, terminated, item_key, ret, disc, nlen, head,
                         ep_start, open_from, rows, n, powers, obs, act, rew, items)
    if m == 0:
        return 0, 0, identity, queue_head
    queue_head = take_slots(slots[:m], free, num_free, slot_key, queue, queue_head, tail)  # (cannot run out:
    n_free = min(m, num_free)  # the caller checked B <= the table's size)
    write_records(slot_ref, slot_rows, slots[:m], items[:m], ret, disc)
    identity = insert_slots(slots[:m], n_free, inserted, slot_key, priority, max_priority, times_sampled, dense, where,
                            size, identity, queue, tail, keys[:m])
    for j in range(m):
        item_key[items[j, 1]] = keys[j]
    return m, n_free, identity, queue_head


def bind_batched_step(w: TransitionWriter) -> Callable[[TransitionWriter, Transition], bool]:
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


def batched_step(w: TransitionWriter, t: Transition, columns: tuple[np.ndarray, ...]) -> bool:
    """Append step `t` of a B-env TransitionWriter in which no episode ended, and insert the
    items it closes: `_Writer._flush_one`'s NumPy path, compiled. `columns`: `_flat_columns(w)`.
    Returns whether the fused path (`_step_and_insert`) took it."""
    s, table = w.store, w.table
    b = s.B
    frames = t.obs[:, -1] if s.k > 1 else t.obs
    items = np.empty((b, 3), np.int64)
    if not s.on_device:
        frames_np = np.ascontiguousarray(to_numpy(frames)).reshape(b, -1)
        actions_np = np.ascontiguousarray(to_numpy(t.action)).reshape(b, -1)
        rewards = np.ascontiguousarray(to_numpy(t.reward)).reshape(b)
        if _fused_step(w, columns, frames_np, actions_np, rewards, items):
            return True
    stamp, item_key = columns[3], columns[7]
    evict = np.empty(b, np.int64)
    count = _evictable(stamp, item_key, table.slot_key, s.head, s.T, s.k, evict)
    if count:
        table.delete(evict[:count])
    if s.on_device:  # the rows this step takes; the loops write the bookkeeping, torch the data
        rows = s.head_rows()
        s._put("frame", rows, frames)
        s._put("action", rows, t.action)
        frames_np = actions_np = np.empty((b, 0), np.float32)
        rewards = np.ascontiguousarray(to_numpy(t.reward)).reshape(b)
    m = _write_and_close(*columns, s.head, s.ep_start, w._open_from, s.T, w.n, w.powers, frames_np, actions_np,
                         rewards, items)
    if m:
        item_key[items[:m, 1]] = table.insert_batch(items[:m], n=m)
    return False


def _fused_step(w: TransitionWriter, columns: tuple[np.ndarray, ...], frames: np.ndarray, actions: np.ndarray,
                rewards: np.ndarray, items: np.ndarray) -> bool:
    """`_step_and_insert` under the table's lock when the table can take B items at once
    without waiting (a Uniform/Fifo table, a non-blocking rate limiter); False, with nothing
    written, when it cannot or when a row's reuse needs a delete first."""
    s, table = w.store, w.table
    b = s.B
    if table._insert_kernels is None or table.storage is not w or b > table.max_size:
        return False
    sampler, remover = table.sampler, table.remover
    with table._cv:
        if table.inserts_wait and table.rate_limiter.inserts_available() < b:
            return False
        remover.reserve(b)
        slots = np.empty(b, np.int64)
        keys = np.empty(b, np.int64)
        m, n_free, identity, queue_head = _step_and_insert(
            *columns, s.head, s.ep_start, w._open_from, s.T, w.n, s.k, w.powers, frames, actions, rewards, items,
            w.slot_ref, w.slot_rows, table.slot_key, table._free, table._num_free, table._inserted, table.priority,
            table.max_priority, table.times_sampled, sampler.dense, sampler.where, sampler.size, sampler.identity,
            remover.queue, remover.head, remover.tail, slots, keys)
        if m < 0:
            return False
        if m:
            sampler.identity = identity
            remover.head = queue_head
            table.note_inserted(m, n_free)
            if table._waiting:
                table._cv.notify_all()
    return True
