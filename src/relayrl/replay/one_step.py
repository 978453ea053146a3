"""One env, one staged step: a TransitionWriter's flush in Python scalars.

A 1:1 collect/train loop (the DQN tutorial's collect_steps=1 with one env) flushes after
every env step. The general path spends ~60 NumPy calls on arrays of one element (~270 us
a step); this path reads and writes single elements of the same columns (~25 us). It writes
exactly what the general path writes, episode ends included; tests/test_replay_writers.py
checks the two against each other.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from relayrl.arrays import to_numpy
from relayrl.types import Transition

if TYPE_CHECKING:
    from relayrl.replay.writers import TransitionWriter


def row_value(x: Any) -> Any:
    """Row 0 of a batch of one: a Python scalar when it holds one value (cheaper than a view)."""
    if isinstance(x, torch.Tensor):
        return x.item() if x.numel() == 1 else to_numpy(x)[0]
    x = np.asarray(x)
    return x.item() if x.size == 1 else x[0]


def one_env_step(w: TransitionWriter, t: Transition) -> None:
    """Append step `t` of a one-env TransitionWriter (and its final row if the episode
    ended), then insert the items it closes: the general `flush` for C = B = 1."""
    s = w.store
    T, k = s.T, s.k
    term = bool(t.terminated)
    done = term or bool(t.truncated)
    pos = int(s.head[0])
    start = int(s.ep_start[0])
    _evict(w, pos, 2 if done else 1)
    obs = to_numpy(t.obs)[0]
    _write_row(w, pos, start, obs[-1] if k > 1 else obs, row_value(t.reward), last=False, terminated=False)
    w._action[pos % T] = row_value(t.action)
    if done:
        final = to_numpy(t.next_obs)[0]
        _write_row(w, pos + 1, start, final[-1] if k > 1 else final, 0.0, last=True, terminated=term)
        s.head[0] = s.ep_start[0] = pos + 2
    else:
        s.head[0] = pos + 1
    _close(w, pos, done, term)


def _write_row(w: TransitionWriter, pos: int, start: int, frame: np.ndarray, reward: float, *,
               last: bool, terminated: bool) -> None:
    """StepStore._write_rows for one row of env 0 (a final row's action is left as it was)."""
    r = pos % w.store.T
    w._frame[r] = frame
    w._reward[r] = reward
    w._stamp[r] = pos + 1
    w._start[r] = start
    w._last[r] = last
    w._terminated[r] = terminated
    w._item_key[r] = -1


def _evict(w: TransitionWriter, pos: int, count: int) -> None:
    """StepStore.evictable + _Writer._evict for positions pos .. pos+count-1 of env 0: one
    `Table.delete` for all, as the general path, so slots are freed in the same order."""
    s, table = w.store, w.table
    keys = []
    for p in range(pos - s.T + s.k - 1, pos - s.T + s.k - 1 + count):  # the newest item reading each row
        r = p % s.T
        if p >= 0 and w._stamp[r] == p + 1:
            key = int(w._item_key[r])
            if key >= 0 and table.slot_key[key % table.max_size] == key:
                keys.append(key)
    if keys:
        table.delete(np.array(keys, dtype=np.int64))


def _close(w: TransitionWriter, pos: int, done: bool, term: bool) -> None:
    """TransitionWriter._close_items after row `pos` (and a final row at pos + 1 if done)."""
    T, n, powers = w.store.T, w.n, w.powers
    first = int(w._open_from[0])
    newest = pos if done else pos - n  # without an episode end only the item at pos - n closes
    w._open_from[0] = pos + 2 if done else max(first, newest + 1)
    if newest < first:
        return
    items = []
    for q in range(first, newest + 1):
        if done and pos + 1 - q <= n:  # the window reaches the final row at pos + 1
            length, nxt = pos + 1 - q, pos + 1
            disc = 0.0 if term else powers[length]
        else:
            length, nxt, disc = n, q + n, powers[n]
        ret = 0.0
        for m in range(length):  # the general path's products, summed in its order
            ret += float(w._reward[(q + m) % T]) * powers[m]
        i = q % T
        w._ret[i] = ret
        w._disc[i] = disc
        w._nlen[i] = length
        items.append((q, i, nxt % T))  # env 0: ref = q, flat rows = rows of the ring
    keys = w.table.insert_batch(np.array(items, dtype=np.int64), n=len(items))
    for (_, i, _), key in zip(items, keys.tolist(), strict=True):
        w._item_key[i] = key
