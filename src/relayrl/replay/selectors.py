"""Item selectors, used as a Table's sampler or its remover (as in Reverb).

A selector tracks the table's live items by slot. The table tells it about inserts,
priority updates and deletes, and asks it to `select` items to sample or `pop` items to
remove. Each selector keeps only what its order needs: a dense slot list (Uniform), a sum
tree (Prioritized), a key queue (Fifo, Lifo) or a heap (MaxHeap, MinHeap). Queues and heaps
delete lazily: stale entries are skipped when they reach the front, and the structure is
compacted when stale entries outnumber live ones.
"""

from __future__ import annotations

import heapq
from functools import partial
from typing import Any

import numpy as np

from relayrl.compile import numba_available
from relayrl.replay.sumtree import SumTree


def make_sum_tree(capacity: int) -> tuple[Any, bool]:
    """The compiled tree (`sumtree_fast.CompiledSumTree`) where numba runs, else the NumPy
    `sumtree.SumTree` (same interface, same leaves found); and whether it is the compiled one."""
    if numba_available():
        from relayrl.replay.sumtree_fast import CompiledSumTree
        return CompiledSumTree(capacity), True
    return SumTree(capacity), False


class Selector:
    """Base class. `slot_key[slot]` is the live key in a slot (-1 when empty)."""

    def bind(self, capacity: int, slot_key: np.ndarray, priority: np.ndarray) -> None:
        if getattr(self, "slot_key", None) is not None:  # two tables' items in one index: both sample wrong
            raise ValueError(f"this {type(self).__name__} already selects for another table: give each table its "
                             f"own (sampler={type(self).__name__}(), ...)")
        self.capacity = capacity
        self.slot_key = slot_key
        self.priority = priority
        self.size = 0

    def insert(self, slots: np.ndarray, keys: np.ndarray) -> None:
        self.size += len(slots)

    def replace(self, slots: np.ndarray, keys: np.ndarray) -> None:
        """Slots whose old items were deleted and immediately refilled (a full table's insert)."""
        self.delete(slots)
        self.insert(slots, keys)

    def update(self, slots: np.ndarray) -> None:
        """Priorities of `slots` changed (already written to `self.priority`)."""

    def delete(self, slots: np.ndarray) -> None:
        self.size -= len(slots)

    def select(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """n slots (with repetition) and the probability each had of being selected."""
        raise NotImplementedError

    def select_items(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """`select`, plus the key and priority in each slot selected."""
        slots, probs = self.select(n, rng)
        return slots, probs, self.slot_key.take(slots), self.priority.take(slots)

    # Set by a selector that can do a table's whole update_priorities in one compiled pass:
    # (keys, priorities) -> the largest priority written, -1.0 if no key was live.
    update_keys: Any = None

    def pop(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """n distinct slots to remove (the table deletes them afterwards)."""
        raise NotImplementedError

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any], live_slots: np.ndarray) -> None:
        """Rebuild from the table's live slots (in key order) and any saved order state."""
        self.size = 0
        self.insert(live_slots, self.slot_key[live_slots])

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


class Uniform(Selector):
    """Every live item equally likely. O(1) insert, delete and sample."""

    def bind(self, capacity: int, slot_key: np.ndarray, priority: np.ndarray) -> None:
        super().bind(capacity, slot_key, priority)
        self.dense = np.zeros(capacity, dtype=np.int64)  # live slots in [0, size)
        self.where = np.full(capacity, -1, dtype=np.int64)  # slot -> index into dense
        # dense[:size] == arange(size), as it stays while a table fills its free slots in order
        # and a FIFO remover refills them: a sample then needs no gather through `dense`.
        self.identity = True

    def insert(self, slots: np.ndarray, keys: np.ndarray) -> None:
        n, size = len(slots), self.size
        if n == 1:
            slot = int(slots[0])
            self.dense[size] = slot
            self.where[slot] = size
            self.identity = self.identity and slot == size
        else:
            at = np.arange(size, size + n)
            self.dense[size:size + n] = slots
            self.where[slots] = at
            if self.identity:
                self.identity = bool((slots == at).all())  # (one compare: cheaper than np.diff)
        self.size = size + n

    def replace(self, slots: np.ndarray, keys: np.ndarray) -> None:
        pass  # same slots, still live: the dense list does not change

    def delete(self, slots: np.ndarray) -> None:
        self.identity = False
        for slot in np.asarray(slots).tolist():  # swap-remove, one slot at a time
            i = self.where[slot]
            last = self.dense[self.size - 1]
            self.dense[i] = last
            self.where[last] = i
            self.where[slot] = -1
            self.size -= 1

    def select(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        idx = rng.integers(0, self.size, n)
        return (idx if self.identity else self.dense.take(idx)), np.full(n, 1.0 / self.size)

    def pop(self, n: int, rng: np.random.Generator) -> np.ndarray:
        return self.dense[rng.choice(self.size, n, replace=False)]

    def state_dict(self) -> dict[str, Any]:
        return {"dense": self.dense[: self.size].copy()}

    def load_state_dict(self, state: dict[str, Any], live_slots: np.ndarray) -> None:
        dense = np.asarray(state.get("dense", live_slots), dtype=np.int64)
        self.size = 0
        self.where[:] = -1
        self.identity = True
        self.insert(dense, self.slot_key[dense])


class Prioritized(Selector):
    """P(i) = p_i^a / sum_k p_k^a (Schaul et al. 2016), a = `priority_exponent`. O(log n)."""

    def __init__(self, priority_exponent: float = 0.6) -> None:
        if priority_exponent < 0:
            raise ValueError(f"priority_exponent={priority_exponent} is not valid; it must be >= 0")
        self.priority_exponent = priority_exponent

    def bind(self, capacity: int, slot_key: np.ndarray, priority: np.ndarray) -> None:
        super().bind(capacity, slot_key, priority)
        self.tree, self.compiled = make_sum_tree(capacity)
        if self.compiled:
            self.update_keys = partial(self.tree.update_live, slot_key, priority, exponent=self.priority_exponent)

    def insert(self, slots: np.ndarray, keys: np.ndarray) -> None:
        self.tree.set_power(slots, self.priority, self.priority_exponent)
        self.size += len(slots)

    def replace(self, slots: np.ndarray, keys: np.ndarray) -> None:
        self.tree.set_power(slots, self.priority, self.priority_exponent)

    def update(self, slots: np.ndarray) -> None:
        self.tree.set_power(slots, self.priority, self.priority_exponent)

    def delete(self, slots: np.ndarray) -> None:
        self.tree.set(slots, np.zeros(len(slots)))
        self.size -= len(slots)

    def select(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        total = self.tree.total
        if total <= 0.0:  # every priority is zero: fall back to uniform over live items
            live = np.flatnonzero(self.slot_key >= 0)
            return live[rng.integers(0, live.size, n)], np.full(n, 1.0 / live.size)
        return self.tree.sample(rng.random(n))

    def select_items(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        if not self.compiled or self.tree.total <= 0.0:
            return super().select_items(n, rng)
        return self.tree.sample_items(rng.random(n), self.slot_key, self.priority)

    def pop(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """n distinct slots, each drawn by priority from the items not drawn yet; once those
        have zero total priority, uniformly among them."""
        chosen: list[int] = []
        taken: set[int] = set()
        while len(chosen) < n:
            slot = int(self.select(1, rng)[0][0]) if self.tree.total > 0.0 else -1
            if slot < 0 or slot in taken:  # nothing left with mass (or only rounding residue)
                rest = np.setdiff1d(np.flatnonzero(self.slot_key >= 0), chosen)
                slot = int(rest[rng.integers(0, rest.size)])
            chosen.append(slot)
            taken.add(slot)
            self.tree.set(np.array([slot]), np.zeros(1))
        self.tree.set_power(np.array(chosen), self.priority, self.priority_exponent)  # the table deletes them
        return np.array(chosen, dtype=np.int64)

    def __repr__(self) -> str:
        return f"Prioritized(priority_exponent={self.priority_exponent})"


class _KeyQueue(Selector):
    """Items ordered by key (insertion order); `front` is the oldest (Fifo) or newest (Lifo).

    Keys wait in a NumPy array between `head` and `tail`; a popped batch is checked for
    stale (deleted) keys with one gather, so removing 1,024 items is a few array calls.
    """

    newest_first = False

    def bind(self, capacity: int, slot_key: np.ndarray, priority: np.ndarray) -> None:
        super().bind(capacity, slot_key, priority)
        self.queue = np.zeros(1024, dtype=np.int64)
        self.head = self.tail = 0

    def insert(self, slots: np.ndarray, keys: np.ndarray) -> None:
        n = len(keys)
        self.reserve(n)
        if n == 1:
            self.queue[self.tail] = keys[0]
        else:
            self.queue[self.tail:self.tail + n] = keys
        self.tail += n
        self.size += len(slots)

    def reserve(self, n: int) -> None:
        """Room for n more keys at the tail (compacting first if there is none); the table's
        compiled insert writes them there itself."""
        if self.tail + n > self.queue.size:
            self._compact(n)

    def trim(self) -> None:
        """Compact once stale keys and popped space outweigh the live keys (after deletes)."""
        if self.tail - self.head > 2 * self.size + 1024:
            self._compact()

    def _compact(self, extra: int = 0) -> None:
        """Drop stale keys and popped space; grow so that `extra` more keys fit."""
        q = self.queue[self.head:self.tail]
        q = q[self.slot_key.take(q % self.capacity) == q]
        size = max(1024, 2 * (q.size + extra))
        if size > self.queue.size or size < self.queue.size // 4:
            self.queue = np.zeros(size, dtype=np.int64)
        self.queue[:q.size] = q
        self.head, self.tail = 0, q.size

    def delete(self, slots: np.ndarray) -> None:
        self.size -= len(slots)  # queue entries go stale; skipped at the front
        self.trim()

    def _live(self, key: int) -> bool:
        return bool(self.slot_key[key % self.capacity] == key)

    def _front(self) -> int:
        q = self.queue
        if self.newest_first:
            while not self._live(int(q[self.tail - 1])):
                self.tail -= 1
            return int(q[self.tail - 1])
        while not self._live(int(q[self.head])):
            self.head += 1
        return int(q[self.head])

    def select(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        slot = self._front() % self.capacity
        return np.full(n, slot, dtype=np.int64), np.ones(n)

    def pop(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """The n front keys' slots, front first; stale keys on the way are dropped."""
        if n == 1:  # a per-step insert into a full table: scalars
            key = self._front()
            if self.newest_first:
                self.tail -= 1
            else:
                self.head += 1
            return np.array([key % self.capacity])
        out: list[np.ndarray] = []
        need = n
        while need > 0:
            if self.newest_first:
                lo = max(self.head, self.tail - need)
                keys = self.queue[lo:self.tail][::-1]
                self.tail = lo
            else:
                hi = min(self.tail, self.head + need)
                keys = self.queue[self.head:hi]
                self.head = hi
            if keys.size == 0:
                raise IndexError("pop from an empty queue")
            slots = keys % self.capacity
            live = self.slot_key.take(slots) == keys
            out.append(slots if np.count_nonzero(live) == live.size else slots[live])
            need -= out[-1].size
        return out[0] if len(out) == 1 else np.concatenate(out)

    def load_state_dict(self, state: dict[str, Any], live_slots: np.ndarray) -> None:
        self.head = self.tail = 0
        super().load_state_dict(state, live_slots)


class Fifo(_KeyQueue):
    """The oldest item first."""


class Lifo(_KeyQueue):
    """The newest item first."""

    newest_first = True


class _Heap(Selector):
    """Items ordered by priority; ties go to the least recently inserted or updated item, as
    in Reverb's heap. O(log n) insert and update.

    Every insert and update stamps its slot with a new sequence number and pushes an entry
    (sign * priority, stamp, slot). An entry is live while its slot's stamp is still its own,
    so an update leaves exactly one live entry per item, whatever the priorities.
    """

    sign = 1.0  # +1: smallest priority at the front (MinHeap); -1: largest (MaxHeap)

    def bind(self, capacity: int, slot_key: np.ndarray, priority: np.ndarray) -> None:
        super().bind(capacity, slot_key, priority)
        self.heap: list[tuple[float, int, int]] = []
        self.stamp = np.full(capacity, -1, dtype=np.int64)  # slot -> stamp of its live entry (-1: none)
        self.next_stamp = 0

    def _push(self, slots: np.ndarray) -> None:
        for slot in np.asarray(slots).tolist():
            stamp = self.next_stamp
            self.next_stamp += 1
            self.stamp[slot] = stamp
            heapq.heappush(self.heap, (self.sign * float(self.priority[slot]), stamp, slot))

    def insert(self, slots: np.ndarray, keys: np.ndarray) -> None:
        self._push(slots)
        self.size += len(slots)

    def update(self, slots: np.ndarray) -> None:
        self._push(slots)  # the slot's older entry goes stale: its stamp is no longer the slot's
        self._maybe_compact()

    def delete(self, slots: np.ndarray) -> None:
        self.stamp[slots] = -1
        self.size -= len(slots)
        self._maybe_compact()

    def _maybe_compact(self) -> None:
        if len(self.heap) > 2 * self.size + 1024:
            self.heap = [e for e in self.heap if self._live(e)]
            heapq.heapify(self.heap)

    def _live(self, entry: tuple[float, int, int]) -> bool:
        return bool(self.stamp[entry[2]] == entry[1])

    def _front(self) -> int:
        while not self._live(self.heap[0]):
            heapq.heappop(self.heap)
        return self.heap[0][2]

    def select(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        return np.full(n, self._front(), dtype=np.int64), np.ones(n)

    def pop(self, n: int, rng: np.random.Generator) -> np.ndarray:
        out = []
        for _ in range(n):
            slot = self._front()
            heapq.heappop(self.heap)
            self.stamp[slot] = -1  # popped: none of its entries may come up again before the table deletes it
            out.append(slot)
        return np.array(out, dtype=np.int64)

    def state_dict(self) -> dict[str, Any]:
        live = np.flatnonzero(self.stamp >= 0)
        return {"order": live[np.argsort(self.stamp[live], kind="stable")]}  # oldest insert or update first

    def load_state_dict(self, state: dict[str, Any], live_slots: np.ndarray) -> None:
        self.heap, self.size, self.next_stamp = [], 0, 0
        self.stamp[:] = -1
        order = np.asarray(state.get("order", live_slots), dtype=np.int64)
        self.insert(order, self.slot_key[order])


class MinHeap(_Heap):
    """The item with the smallest priority first."""


class MaxHeap(_Heap):
    """The item with the largest priority first."""

    sign = -1.0
