"""A Table's insert of n items with a Uniform sampler and a Fifo remover (the default table, and
every uniform replay relayrl builds), in compiled loops (numba, the `relayrl[fast]` extra).

`Table._insert_many_locked` spends about twenty NumPy calls on [n] arrays (its own bookkeeping, then each
selector's), whose fixed costs are most of an insert at the batched 1:1 loop's n = B; these
loops do the same writes: free slots first (the free stack's end first), then, in a full
table, the Fifo's oldest live items as victims (as `_KeyQueue.pop` takes them, skipping stale
keys). `Table.insert_batch` calls `insert` under its lock and updates its counters. Priorities
given, other selectors, or no numba (RELAYRL_NUMBA=0) take the NumPy path;
tests/test_replay_table.py checks that both leave the same table.
"""

from __future__ import annotations

import numpy as np

from relayrl.compile import njit


@njit
def take_slots(slots: np.ndarray, free: np.ndarray, num_free: int, slot_key: np.ndarray, queue: np.ndarray,
               head: int, tail: int) -> int:
    """Fill `slots`: free ones off the stack's end, then the Fifo's oldest live items (the
    victims). Returns the queue's new head, or -1 when it ran out of live keys (nothing that
    the caller keeps is changed then: it raises)."""
    n = slots.size
    n_free = min(n, num_free)
    for j in range(n_free):
        slots[j] = free[num_free - 1 - j]
    capacity = slot_key.size
    j = n_free
    while j < n:
        if head >= tail:
            return -1
        key = queue[head]
        head += 1
        if slot_key[key % capacity] == key:  # stale keys (deleted items) are skipped
            slots[j] = key % capacity
            j += 1
    return head


@njit
def insert_slots(slots: np.ndarray, n_free: int, inserted: int, slot_key: np.ndarray, priority: np.ndarray,
                 max_priority: float, times_sampled: np.ndarray, dense: np.ndarray, where: np.ndarray, size: int,
                 identity: bool, queue: np.ndarray, tail: int, keys: np.ndarray) -> bool:
    """Key `slots` insert_count * max_size + slot, reset their priority and sample count, and
    append their keys to the Fifo queue at `tail`. The first `n_free` (free slots) join the
    Uniform sampler's dense list; the rest were victims, live slots already in it. Fills `keys`;
    returns the sampler's new `identity` flag (dense[:size] == arange(size) still holds). The
    caller checked that the queue has room and updates the scalar counters."""
    max_size = slot_key.size
    for j in range(slots.size):
        slot = slots[j]
        key = (inserted + j) * max_size + slot
        keys[j] = key
        slot_key[slot] = key
        priority[slot] = max_priority
        times_sampled[slot] = 0
        if j < n_free:
            dense[size + j] = slot
            where[slot] = size + j
            identity = identity and slot == size + j
        queue[tail + j] = key
    return identity


@njit
def insert(slots: np.ndarray, keys: np.ndarray, free: np.ndarray, num_free: int, inserted: int, slot_key: np.ndarray,
           priority: np.ndarray, max_priority: float, times_sampled: np.ndarray, dense: np.ndarray, where: np.ndarray,
           size: int, identity: bool, queue: np.ndarray, head: int, tail: int) -> tuple[int, bool]:
    """`take_slots`, then `insert_slots` (one call from Python): returns the Fifo queue's new head
    (-1, with nothing written, when it ran out of live keys) and the sampler's identity flag."""
    head = take_slots(slots, free, num_free, slot_key, queue, head, tail)
    if head < 0:
        return head, identity
    identity = insert_slots(slots, min(slots.size, num_free), inserted, slot_key, priority, max_priority,
                            times_sampled, dense, where, size, identity, queue, tail, keys)
    return head, identity
