"""A check both sum trees must pass (imported by test_replay_table and test_sumtree_fast)."""

import numpy as np


def check_updates_and_finds(tree, n: int, seed: int) -> None:
    """Fill, update with repeated indices (the last value wins), then find 20,000 queries:
    never an empty leaf, and the leaves a flat cumulative sum finds, up to boundary rounding."""
    rng = np.random.default_rng(seed)
    values = rng.random(n) * (rng.random(n) < 0.3)  # most leaves empty
    values[rng.integers(0, n)] = 1.0  # at least one with mass
    tree.set(np.arange(n), values)
    for _ in range(30):
        idx = rng.integers(0, n, 300)
        new = rng.random(300) * (rng.random(300) < 0.5)
        tree.set(idx, new)
        for i, v in zip(idx.tolist(), new.tolist(), strict=True):
            values[i] = v
    assert np.array_equal(tree.get(np.arange(n)), values)
    assert np.isclose(tree.total, values.sum())
    if values.sum() == 0:
        return
    u = rng.random(20_000) * tree.total
    found, mass = tree.find_with_mass(u)
    assert (mass > 0).all() and np.array_equal(mass, values[found])
    expected = np.searchsorted(np.cumsum(values), u, side="right")
    assert (found != expected).sum() <= 2  # the two sums round differently only at boundaries
