"""A binary sum tree walked by compiled loops (numba, the `relayrl[fast]` extra).

The NumPy tree in `sumtree.py` answers a batch in a dozen array calls, and at 256 queries
those calls' fixed costs (the top level's cumsum the largest) are the whole bill. Here a
query is a 20-step loop down a flat binary tree and an update a 20-step loop up it.
`selectors.make_sum_tree` picks this class when numba imports; both classes have the same interface and
find the same leaves (the two only round differently, so a query exactly on an interval's
boundary may land one leaf apart).

Layout: `tree[1]` is the total, node i has children 2i and 2i+1, the leaves are
`tree[base:base + capacity]` with `base` the power of two >= capacity. Every update
recomputes its ancestors from their children, so sums never drift.
"""

from __future__ import annotations

import numpy as np

from relayrl.compile import njit
from relayrl.replay.sumtree import SumTreeBase, flat_updates


@njit
def _set(tree: np.ndarray, base: int, idx: np.ndarray, values: np.ndarray) -> None:
    node = idx + base
    for j in range(idx.size):  # in order, so a repeated index keeps its last value
        tree[node[j]] = values[j]
    _update_parents(tree, node)


@njit
def _set_power(tree: np.ndarray, base: int, idx: np.ndarray, priority: np.ndarray, exponent: float) -> None:
    node = idx + base
    zero_power = exponent == 0.0
    for j in range(idx.size):
        p = priority[idx[j]]
        tree[node[j]] = (1.0 if p > 0.0 else 0.0) if zero_power else p ** exponent  # 0 ** 0 must stay 0
    _update_parents(tree, node)


@njit
def _update_parents(tree: np.ndarray, node: np.ndarray) -> None:
    # Level by level across the batch, not index by index: the loads of one level are
    # independent, so the CPU overlaps their cache misses (a 1M-leaf tree is 16 MB).
    # The depth is read from node[0]: an empty batch must not reach it (numba does not
    # bounds-check, and a stray read there never reaches the root).
    if node.size == 0:
        return
    while node[0] > 1:
        for j in range(node.size):
            p = node[j] >> 1
            tree[p] = tree[2 * p] + tree[2 * p + 1]
            node[j] = p


@njit
def _update_live(tree: np.ndarray, base: int, slot_key: np.ndarray, priority: np.ndarray, keys: np.ndarray,
                 prios: np.ndarray, exponent: float, node: np.ndarray) -> float:
    """A table's `update_priorities` in one pass: for each key still live in its slot, write
    its priority and its leaf, then fix the ancestors. Returns the largest priority written,
    -1.0 when no key was live, or -2.0 (nothing written) when a priority is not finite and >= 0."""
    for j in range(prios.size):
        p = prios[j]
        if not (p >= 0.0 and p < np.inf):  # NaN fails both
            return -2.0
    capacity = slot_key.size
    zero_power = exponent == 0.0
    top = -1.0
    n = 0
    for j in range(keys.size):  # in order, so a repeated key keeps its last priority
        key = keys[j]
        if key < 0:
            continue
        slot = key % capacity
        if slot_key[slot] != key:  # deleted, or its slot reused since it was sampled
            continue
        p = prios[j]
        priority[slot] = p
        # 0 ** 0 is 1: a zero priority must stay zero (the branch is on a loop invariant)
        tree[base + slot] = (1.0 if p > 0.0 else 0.0) if zero_power else p ** exponent
        node[n] = base + slot
        n += 1
        top = max(top, p)
    _update_parents(tree, node[:n])
    return top


@njit
def _find(tree: np.ndarray, base: int, u: np.ndarray, scale: float, node: np.ndarray, mass: np.ndarray) -> None:
    if u.size == 0:  # as in `_update_parents`: node[0] below must exist
        return
    x = u * scale
    node[:] = 1
    while node[0] < base:  # every leaf is at the same depth; level by level, as in `_set`
        for j in range(x.size):
            i = 2 * node[j]
            left = tree[i]
            # Go right only into mass: when rounding leaves x >= left under an empty right
            # child, the left child holds all of this node's mass. So no empty leaf is found.
            # Branch-free: random descents mispredict half their branches.
            right = (x[j] >= left) & (tree[i + 1] > 0.0)
            x[j] -= left * right
            node[j] = i + right
    for j in range(x.size):
        mass[j] = tree[node[j]]
        node[j] -= base


@njit
def _find_items(tree: np.ndarray, base: int, u: np.ndarray, node: np.ndarray, prob: np.ndarray,
                slot_key: np.ndarray, priority: np.ndarray, key: np.ndarray, prio: np.ndarray) -> None:
    """`_find` for u in [0, 1), with each leaf's probability, and the table's key and priority
    of each slot found, gathered here while the loop's loads overlap."""
    total = tree[1]
    _find(tree, base, u, total, node, prob)
    for j in range(u.size):
        prob[j] /= total
        key[j] = slot_key[node[j]]
        prio[j] = priority[node[j]]


class CompiledSumTree(SumTreeBase):
    """`SumTree`'s interface on a flat binary tree; see the module docstring."""

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError("SumTree capacity must be >= 1")
        self.capacity = capacity
        self.base = 1 << max(capacity - 1, 1).bit_length()
        self.tree = np.zeros(2 * self.base)
        self.leaves = self.tree[self.base: self.base + capacity]  # a view

    @property
    def total(self) -> float:
        return float(self.tree[1])

    def set(self, idx: np.ndarray, values: np.ndarray) -> None:
        _set(self.tree, self.base, *flat_updates(idx, values))

    def set_power(self, idx: np.ndarray, priority: np.ndarray, exponent: float) -> None:
        """`set(idx, priority[idx] ** exponent)` in one pass."""
        _set_power(self.tree, self.base, np.ascontiguousarray(idx, dtype=np.int64), priority, float(exponent))

    def rebuild(self) -> None:
        level = self.base
        while level > 1:
            half = level // 2
            self.tree[half:level] = self.tree[level: 2 * level: 2] + self.tree[level + 1: 2 * level: 2]
            level = half

    def find_with_mass(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self._find(np.ascontiguousarray(u, dtype=np.float64).reshape(-1), 1.0)

    def sample(self, uniform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        total = self.total
        node, mass = self._find(uniform, total)  # scaled in the loop, with no array for uniform * total
        return node, mass / total

    def update_live(self, slot_key: np.ndarray, priority: np.ndarray, keys: np.ndarray, prios: np.ndarray,
                    exponent: float) -> float:
        """A Table's `update_priorities` for a prioritized sampler (see `_update_live`); raises,
        writing nothing, on a priority not finite and >= 0."""
        keys = np.ascontiguousarray(keys, dtype=np.int64)
        prios = np.ascontiguousarray(prios, dtype=np.float64)
        if keys.size != prios.size:  # the loop reads prios[j] for every key, unchecked
            raise ValueError(f"{keys.size} keys but {prios.size} priorities")
        top = _update_live(self.tree, self.base, slot_key, priority, keys, prios, float(exponent),
                           np.empty(keys.size, np.int64))
        if top == -2.0:
            raise ValueError("priorities must be finite and >= 0")
        return top

    def sample_items(self, uniform: np.ndarray, slot_key: np.ndarray,
                     priority: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """`sample(uniform)` plus `slot_key` and `priority` at the leaves found. The total must be > 0."""
        n = uniform.size
        node, prob = np.empty(n, np.int64), np.empty(n, np.float64)
        key, prio = np.empty(n, np.int64), np.empty(n, np.float64)
        _find_items(self.tree, self.base, uniform, node, prob, slot_key, priority, key, prio)
        return node, prob, key, prio

    def _find(self, u: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
        node = np.empty(u.size, np.int64)
        mass = np.empty(u.size, np.float64)
        if self.tree[1] > 0.0:
            _find(self.tree, self.base, u, scale, node, mass)
        else:  # nothing to find (callers check the total first)
            node[:] = 0
            mass[:] = 0.0
        return node, mass
