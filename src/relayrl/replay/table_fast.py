"""A Table's insert of n items with a Uniform sampler and a Fifo remover (the default table, and
every uniform replay relayrl builds), in compiled loops (numba, the `relayrl[fast]` extra).

`Table._insert_many_locked` spends about twenty NumPy calls on [n] arrays, whose fixed costs
are most of an insert at the batched 1:1 loop's n = B. Priorities given, other selectors, or
no numba (RELAYRL_NUMBA=0) take the NumPy path; tests/test_replay_table.py checks that both
leave the same table.
"""

from __future__ import annotations

import numpy as np

from relayrl.compile import njit


@njit
def insert(slots: np.ndarray, keys: np.ndarray, free: np.ndarray, num_free: int, inserted: int, slot_key: np.ndarray,
           priority: np.ndarray, max_priority: float, times_sampled: np.ndarray, dense: np.ndarray, where: np.ndarray,
           size: int, identity: bool, queue: np.ndarray, head: int, tail: int) -> tuple[int, bool]:
    """`_insert_many_locked`'s writes: fill `slots` with free ones off the stack's end, then the
    Fifo's oldest live items (the victims, stale keys skipped, as `_KeyQueue.pop` takes them);
    key them, reset their priority and sample count, append their keys to the Fifo queue at
    `tail`, and add the free ones to the Uniform sampler's dense list. Returns the queue's new
    head (-1, with nothing the caller keeps written, when it ran out of live keys) and the
    sampler's `identity` flag. The caller made room in the queue and updates the counters."""
    n = slots.size
    n_free = min(n, num_free)
    for j in range(n_free):
        slots[j] = free[num_free - 1 - j]
    max_size = slot_key.size
    j = n_free
    while j < n:
        if head >= tail:
            return -1, identity
        key = queue[head]
        head += 1
        if slot_key[key % max_size] == key:
            slots[j] = key % max_size
            j += 1
    for j in range(n):
        slot = slots[j]
        key = (inserted + j) * max_size + slot
        keys[j] = key
        slot_key[slot] = key
        priority[slot] = max_priority
        times_sampled[slot] = 0
        if j < n_free:  # victims are live slots in the dense list already
            dense[size + j] = slot
            where[slot] = size + j
            identity = identity and slot == size + j
        queue[tail + j] = key
    return head, identity
