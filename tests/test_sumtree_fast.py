"""The compiled sum tree (relayrl[fast]) against a flat cumulative sum and the NumPy tree."""

import numpy as np
import pytest
from tree_checks import check_updates_and_finds

from relayrl.replay import Fifo, MaxHeap, MinSize, Prioritized, Table
from relayrl.replay.selectors import make_sum_tree
from relayrl.replay.sumtree import SumTree

jit = pytest.importorskip("relayrl.replay.sumtree_fast", reason="numba is not installed (pip install relayrl[fast])")
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
    assert type(make_sum_tree(10)[0]) is SumTree
    monkeypatch.setenv("RELAYRL_NUMBA", "1")
    assert type(make_sum_tree(10)[0]) is CompiledSumTree


def _table_after_updates(monkeypatch, numba: str, remover_cls: type) -> tuple[Table, list[int]]:
    monkeypatch.setenv("RELAYRL_NUMBA", numba)
    t = Table("t", 8, Prioritized(0.5), remover_cls(), MinSize(1), seed=0)
    keys = [t.insert(np.int64(i), priority=1.0 + i) for i in range(11)]  # 11 into 8 slots
    gone = [k for k in keys if t.slot_key[k % 8] != k]
    assert len(gone) == 3  # removed to make room (Fifo: the first three; MaxHeap: the largest)
    # Two removed keys, a key never inserted (99 * 8 + 1), -1 (an empty slot's mark), a
    # repeated key (the last value wins) and a zero priority.
    live = [x for x in keys if x not in gone]
    t.update_priorities(np.array([gone[0], live[2], gone[1], 99 * 8 + 1, -1, live[4], live[2], live[0]]),
                        np.array([9.0, 4.0, 9.0, 9.0, 9.0, 0.0, 25.0, 0.5]))
    return t, live


@pytest.mark.parametrize("remover", [Fifo, MaxHeap])
def test_update_priorities_in_one_compiled_pass_matches_numpy(monkeypatch, remover):
    # Fifo: the compiled one-pass update; MaxHeap must see priorities, so the table updates in NumPy.
    (fused, live), (plain, live_p) = (_table_after_updates(monkeypatch, n, remover) for n in ("1", "0"))
    assert live == live_p
    assert (fused._update_keys == fused.sampler.update_keys) == (remover is Fifo)
    expected = {k: 1.0 + k // 8 for k in live} | {live[2]: 25.0, live[4]: 0.0, live[0]: 0.5}
    for t in (fused, plain):
        assert {int(k): float(t.priority[k % 8]) for k in t.slot_key if k >= 0} == expected
        assert t.max_priority == 25.0 and t.size == 8
        assert np.isclose(t.sampler.tree.total, sum(p ** 0.5 for p in expected.values()))
    _, info_f = fused.sample(200)
    _, info_p = plain.sample(200)
    assert np.array_equal(info_f.key, info_p.key) and np.allclose(info_f.probability, info_p.probability)
    assert np.array_equal(info_f.priority, fused.priority[info_f.key % 8]) and live[4] not in info_f.key


@pytest.mark.parametrize("numba", ["1", "0"])
def test_invalid_priorities_change_nothing(monkeypatch, numba):
    t, _ = _table_after_updates(monkeypatch, numba, Fifo)
    before, total = t.priority.copy(), t.sampler.tree.total
    for bad in (np.nan, np.inf, -1.0):
        with pytest.raises(ValueError, match="'t': priorities must be finite and >= 0"):
            t.update_priorities(np.array([4, 6]), np.array([2.0, bad]))
    assert np.array_equal(t.priority, before) and t.sampler.tree.total == total


@pytest.mark.parametrize("numba", ["1", "0"])
def test_key_minus_one_never_writes_an_empty_slot(monkeypatch, numba):
    # -1 marks an empty slot in slot_key, and -1 % 8 is slot 7: a bare liveness compare would
    # give empty slot 7 a priority (and the tree mass there to be found).
    monkeypatch.setenv("RELAYRL_NUMBA", numba)
    t = Table("t", 8, Prioritized(1.0), Fifo(), MinSize(1), seed=0)
    for i in range(3):
        t.insert(np.int64(i), priority=1.0)
    t.update_priorities(np.array([-1]), np.array([50.0]))
    assert t.priority[7] == 0.0 and t.sampler.tree.total == 3.0 and t.max_priority == 1.0
