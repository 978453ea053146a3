"""A Table's insert of n items into free slots, with a Uniform sampler and a Fifo remover (the
default table, and every uniform replay relayrl builds), in one compiled loop (numba, the
`relayrl[fast]` extra).

`Table._insert_many_locked` spends ~20 NumPy calls on [n] arrays (its own bookkeeping, then each
selector's); at n = 32 that is ~40 us, twice that between env steps, on the batched 1:1 loop's
every step. This loop does the same writes in ~3 us. A full table (Fifo victims), priorities
given, other selectors, or no numba (RELAYRL_NUMBA=0) take the NumPy path; tests/test_replay_table.py
checks that both leave the same table.
"""

from __future__ import annotations

import numpy as np

from relayrl.replay.sumtree_jit import _compile


@_compile
def insert_free(slots: np.ndarray, inserted: int, slot_key: np.ndarray, priority: np.ndarray, max_priority: float,
                times_sampled: np.ndarray, dense: np.ndarray, where: np.ndarray, size: int, identity: bool,
                queue: np.ndarray, tail: int, keys: np.ndarray) -> bool:
    """Key the free `slots` insert_count * max_size + slot, reset their priority and sample
    count, append them to the Uniform sampler's dense list and their keys to the Fifo queue at
    `tail`. Fills `keys`; returns the sampler's new `identity` flag (dense[:size] ==
    arange(size) still holds). The caller took the slots off the free stack, checked that the
    queue has room, and updates the scalar counters."""
    max_size = slot_key.size
    for j in range(slots.size):
        slot = slots[j]
        key = (inserted + j) * max_size + slot
        keys[j] = key
        slot_key[slot] = key
        priority[slot] = max_priority
        times_sampled[slot] = 0
        dense[size + j] = slot
        where[slot] = size + j
        identity = identity and slot == size + j
        queue[tail + j] = key
    return identity
