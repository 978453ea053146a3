"""The compiled sum tree (relayrl[fast]) against a flat cumulative sum and the NumPy tree."""

import numpy as np
import pytest
from tree_checks import check_updates_and_finds

from relayrl.replay import Fifo, MinSize, Prioritized, Table
from relayrl.replay.sumtree import SumTree, make_sum_tree

jit = pytest.importorskip("relayrl.replay.sumtree_jit", reason="numba is not installed (pip install relayrl[fast])")
CompiledSumTree = jit.CompiledSumTree


@pytest.mark.parametrize("n", [1, 2, 3, 1_000, 5_000])
def test_find_matches_a_flat_cumulative_sum_after_updates(n):
    check_updates_and_finds(CompiledSumTree(n), n, seed=n)


@pytest.mark.parametrize("tree_class", [SumTree, CompiledSumTree])
def test_empty_updates_and_queries_change_nothing(tree_class):
    # The compiled loops read the tree's depth from their first index: an empty batch once
    # read past the array and never ended.
    tree = tree_class(1_000)
    tree.set(np.arange(10), np.ones(10))
    tree.set(np.array([], np.int64), np.array([]))
    tree.set_power(np.array([], np.int64), np.ones(1_000), 0.6)
    found, mass = tree.find_with_mass(np.array([]))
    assert found.size == 0 and mass.size == 0 and tree.total == 10.0


def test_a_query_at_the_total_lands_on_the_last_leaf_with_mass():
    tree = CompiledSumTree(8)
    tree.set(np.array([1, 5]), np.array([1.0, 2.0]))  # leaves 6, 7 empty
    found, mass = tree.find_with_mass(np.array([0.0, 0.999, 1.0, 2.999, 3.0, 7.0]))
    assert found.tolist() == [1, 1, 5, 5, 5, 5] and mass.tolist() == [1.0, 1.0, 2.0, 2.0, 2.0, 2.0]


def test_set_power_sample_and_state_round_trip_match_the_numpy_tree():
    rng = np.random.default_rng(0)
    priority = rng.uniform(0.01, 2.0, 1_000)
    a, b = SumTree(1_000), CompiledSumTree(1_000)
    for tree in (a, b):
        tree.set_power(np.arange(1_000), priority, 0.6)
    assert np.allclose(a.leaves[:1_000], b.leaves) and np.isclose(a.total, b.total)
    u = rng.random(4_096)
    (na, pa), (nb, pb) = a.sample(u), b.sample(u)
    assert np.array_equal(na, nb) and np.allclose(pa, pb) and np.allclose(pb, priority[nb] ** 0.6 / b.total)
    c = CompiledSumTree(1_000)
    c.load_state_dict(b.state_dict())
    assert np.array_equal(c.tree, b.tree)


def test_tables_sample_the_same_items_with_either_tree(monkeypatch):
    def run(numba: str) -> tuple[list[int], type]:
        monkeypatch.setenv("RELAYRL_NUMBA", numba)
        t = Table("t", 500, Prioritized(0.6), Fifo(), MinSize(1), seed=3)
        rng = np.random.default_rng(1)
        for i in range(700):  # wraps: FIFO removals zero leaves
            t.insert(np.int64(i), priority=float(rng.uniform(0.1, 2.0)))
        keys = []
        for _ in range(20):
            info = t.sample(64)[1]
            keys += info.key.tolist()
            t.update_priorities(info.key, rng.uniform(0.0, 2.0, 64))
        return keys, type(t.sampler.tree)

    (compiled, ctype), (plain, ptype) = run("1"), run("0")
    assert ctype is CompiledSumTree and ptype is SumTree
    assert compiled == plain


def test_without_numba_the_numpy_tree_is_used(monkeypatch):
    monkeypatch.setenv("RELAYRL_NUMBA", "0")
    assert type(make_sum_tree(10)) is SumTree
    monkeypatch.setenv("RELAYRL_NUMBA", "1")
    assert type(make_sum_tree(10)) is CompiledSumTree
