"""`StepStorage.write` of several items in one compiled loop (numba, the `relayrl[fast]` extra).

The NumPy path builds the records with a handful of array calls, whose fixed costs are most
of a 32-item insert's time. Without numba, or with RELAYRL_NUMBA=0 (or `fast=False`), the
NumPy path runs; tests/test_replay_writers.py checks that both leave the same slot map.
"""

from __future__ import annotations

import numpy as np

from relayrl.compile import njit


@njit
def write_records(slot_ref: np.ndarray, slot_rows: np.ndarray, slots: np.ndarray, items: np.ndarray,
                  ret: np.ndarray, disc: np.ndarray, slot_key: np.ndarray, item_key: np.ndarray) -> None:
    """Each slot's ref and its record (row, next row, and the row's return and discount), and
    each item's key at its row."""
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
