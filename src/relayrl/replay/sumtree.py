"""A sum tree for prioritized sampling, vectorised over batches of queries in NumPy.

Leaves are grouped `fanout` at a time, the group totals again, until at most `top_size`
nodes remain (one grouped level for 1,000,000 leaves: 31,250 groups of 32). A batch of
queries finds its top nodes with one cumulative sum and one `searchsorted`, then descends a
grouped level with one row gather, one row-wise cumsum, one compare and one argmax, for all
queries at once. An update writes the leaves and recomputes the totals of the groups it
touched, level by level, from their children: sums never drift, so nothing is rebuilt.

Prefix sums are left-to-right, so a child with zero mass has an empty interval and is never
found. A group's stored total (a NumPy sum) may differ from its children's prefix by rounding,
which can only put a query past the row's end: it then takes the last child. `find` checks
the leaves it returns; should one ever be empty, the query moves to the nearest non-empty
leaf before it.
"""

from __future__ import annotations

import numpy as np
import torch


def flat_updates(idx: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`set`'s arguments as contiguous int64 indices and float64 values of the same length
    (one value broadcasts)."""
    idx = np.ascontiguousarray(idx, dtype=np.int64).reshape(-1)
    values = np.ascontiguousarray(values, dtype=np.float64).reshape(-1)
    if values.size != idx.size:
        values = np.full(idx.size, values[0]) if values.size == 1 else values.reshape(idx.shape)
    return idx, values


class SumTreeBase:
    """What both trees (this module's and `sumtree_fast.CompiledSumTree`) do alike, over their
    `leaves`, `find_with_mass`, `total` and `rebuild`."""

    capacity: int
    leaves: np.ndarray

    @property
    def total(self) -> float:
        raise NotImplementedError

    def find_with_mass(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Leaf indices i with prefix(i) <= u < prefix(i) + leaf(i), for u in [0, total), and
        the values of the leaves found."""
        raise NotImplementedError

    def rebuild(self) -> None:
        """Recompute every total from the leaves."""
        raise NotImplementedError

    def get(self, idx: np.ndarray) -> np.ndarray:
        return self.leaves.take(idx)

    def find(self, u: np.ndarray) -> np.ndarray:
        return self.find_with_mass(u)[0]

    def sample(self, uniform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`find_with_mass(uniform * total)` for `uniform` in [0, 1), and each leaf's
        probability (mass / total). The total must be > 0."""
        total = self.total
        node, mass = self.find_with_mass(uniform * total)
        return node, mass / total

    def state_dict(self) -> dict[str, np.ndarray]:
        return {"leaves": self.leaves[: self.capacity].copy()}

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        leaves = np.asarray(state["leaves"], dtype=np.float64)
        self.leaves[:] = 0.0
        self.leaves[: leaves.size] = leaves
        self.rebuild()


class SumTree(SumTreeBase):
    def __init__(self, capacity: int, fanout: int = 32, top_size: int = 32768) -> None:
        if capacity < 1:
            raise ValueError("SumTree capacity must be >= 1")
        if fanout < 2:
            raise ValueError("SumTree fanout must be >= 2")
        self.capacity = capacity
        self.fanout = f = fanout
        top, depth = capacity, 0
        while top > top_size:
            top, depth = -(-top // f), depth + 1
        self.leaves = np.zeros(top * f**depth)
        # sums[0] is the leaves, sums[d + 1][g] the total of group g of sums[d]; sums[-1] is the top.
        self.sums = [self.leaves]
        for d in range(depth):
            self.sums.append(np.zeros(self.sums[d].size // f))
        self._top_cs = np.zeros(top + 1)  # [0, cumsum(top)], recomputed lazily after writes
        self._top_stale = False
        self._offsets: dict[int, np.ndarray] = {}

    @property
    def total(self) -> float:
        return float(self._top_prefix()[-1])

    def set(self, idx: np.ndarray, values: np.ndarray) -> None:
        idx, values = flat_updates(idx, values)
        leaves = self.leaves
        leaves[idx] = values
        if idx.size > 1 and np.count_nonzero(leaves.take(idx) != values):
            # Repeated indices with different values: the last one wins, as with plain assignment.
            last = idx.size - 1 - np.unique(idx[::-1], return_index=True)[1]
            leaves[idx.take(last)] = values.take(last)
        f = self.fanout
        for d in range(len(self.sums) - 1):
            # Repeated parents are harmless: the same total is written twice.
            idx = idx // f
            self.sums[d + 1][idx] = self.sums[d].reshape(-1, f).take(idx, axis=0).sum(axis=1)
        self._top_stale = True

    def set_power(self, idx: np.ndarray, priority: np.ndarray, exponent: float) -> None:
        """`set(idx, priority[idx] ** exponent)`, where a zero priority stays zero for every
        exponent (Reverb's rule: 0 ** 0 would give a zero-priority item a chance)."""
        p = priority.take(idx)
        values = np.power(p, exponent)
        if exponent == 0.0:
            values[p == 0.0] = 0.0
        self.set(idx, values)

    def rebuild(self) -> None:
        f = self.fanout
        for d in range(len(self.sums) - 1):
            self.sums[d + 1][:] = self.sums[d].reshape(-1, f).sum(axis=1)
        self._top_stale = True

    def _top_prefix(self) -> np.ndarray:
        if self._top_stale:
            torch.cumsum(torch.from_numpy(self.sums[-1]), 0, out=torch.from_numpy(self._top_cs[1:]))
            self._top_stale = False
        return self._top_cs

    def find_with_mass(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        f = self.fanout
        u = np.array(u, dtype=np.float64).reshape(-1)  # a copy: it is consumed level by level
        cs = self._top_prefix()
        node = cs.searchsorted(u, side="right") - 1  # the last top node whose prefix is <= u
        np.minimum(node, cs.size - 2, out=node)  # u >= total (rounding): the last node
        u -= cs.take(node)
        for d in range(len(self.sums) - 2, -1, -1):
            rows = self.sums[d].reshape(-1, f).take(node, axis=0)  # [n, f] children
            inc = torch.cumsum(torch.from_numpy(rows), 1).numpy()  # [n, f] inclusive prefix sums (torch's scan: faster)
            child = (inc > u[:, None]).argmax(axis=1)  # the first child whose interval ends above u
            over = inc[:, -1] <= u  # rounding put u past the group's total: the last child
            if np.count_nonzero(over):
                child[over] = f - 1
            if d:  # on to the child's own children: subtract the children before it
                before = inc.take(self._offset(u.size) + child - 1, mode="wrap")
                before[child == 0] = 0.0
                u -= before
            node = node * f + child
        mass = self.leaves.take(node)
        if np.count_nonzero(mass <= 0):
            node, mass = self._nonempty(node, mass)
        return node, mass

    def _offset(self, n: int) -> np.ndarray:
        """Flat index of row r of an [n, fanout] array: r * fanout."""
        off = self._offsets.get(n)
        if off is None:
            off = self._offsets[n] = np.arange(n, dtype=np.int64) * self.fanout
        return off

    def _nonempty(self, node: np.ndarray, mass: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Move queries that rounding sent to an empty leaf to the nearest non-empty leaf
        before it (or the first one). Never seen; here so that it cannot happen."""
        live = np.flatnonzero(self.leaves > 0)
        if live.size == 0:
            return node, mass
        bad = mass <= 0
        node = node.copy()
        node[bad] = live[np.maximum(np.searchsorted(live, node[bad], side="right") - 1, 0)]
        return node, self.leaves.take(node)
