"""Table semantics: selectors as samplers and removers, rate limiters, keys, checkpoints."""

import threading
import time

import numpy as np
import pytest

from relayrl.replay import (
    Fifo,
    Lifo,
    MaxHeap,
    MinHeap,
    MinSize,
    Prioritized,
    Queue,
    RateLimiterTimeout,
    SampleToInsertRatio,
    Table,
    Uniform,
)
from relayrl.replay.sumtree import SumTree


def filled(max_size, n, sampler=None, remover=None, limiter=None, prios=None, **kw):
    t = Table("t", max_size, sampler or Uniform(), remover or Fifo(), limiter or MinSize(1), seed=0, **kw)
    for i in range(n):
        t.insert(np.int64(i), priority=None if prios is None else prios[i])
    return t


def contents(t):
    live = np.flatnonzero(t.slot_key >= 0)
    return sorted(t.storage.read(live).tolist())


# ---- removers -----------------------------------------------------------------------
@pytest.mark.parametrize("remover, kept", [
    (Fifo, [3, 4, 5]),  # the oldest go first
    (Lifo, [0, 1, 5]),  # each insert into a full table replaces the newest
    (MinHeap, [3, 4, 5]),  # priorities below: the smallest go first
    (MaxHeap, [0, 1, 5]),
])
def test_removers_keep_the_right_items(remover, kept):
    t = filled(3, 6, remover=remover(), prios=[0, 1, 2, 3, 4, 5])
    assert t.size == 3
    assert contents(t) == kept


def test_uniform_remover_removes_live_items_only():
    t = filled(4, 50, remover=Uniform())
    assert t.size == 4 and len(set(contents(t))) == 4 and 49 in contents(t)


# ---- samplers -----------------------------------------------------------------------
def test_uniform_sampler_counts_are_uniform_chi_square():
    t = filled(10, 10)
    items, info = t.sample(20_000)
    counts = np.bincount(items.numpy(), minlength=10)
    chi2 = ((counts - 2_000) ** 2 / 2_000).sum()
    assert chi2 < 27.9  # 9 degrees of freedom, p = 0.001
    assert np.allclose(info.probability, 0.1) and info.table_size == 10


def test_prioritized_sampler_follows_priority_power():
    prios = [1.0, 2.0, 3.0, 4.0]
    t = filled(4, 4, sampler=Prioritized(priority_exponent=2.0), prios=prios)
    items, info = t.sample(30_000)
    expected = np.array(prios) ** 2 / sum(p * p for p in prios)  # 1/30, 4/30, 9/30, 16/30
    counts = np.bincount(items.numpy(), minlength=4)
    chi2 = ((counts - 30_000 * expected) ** 2 / (30_000 * expected)).sum()
    assert chi2 < 16.3  # 3 dof, p = 0.001
    assert np.allclose(info.probability, expected[items.numpy()])
    assert np.allclose(info.priority, np.array(prios)[items.numpy()])


def test_update_priorities_changes_sampling_and_ignores_stale_keys():
    t = filled(3, 3, sampler=Prioritized(1.0), prios=[1.0, 1.0, 1.0])
    _, info = t.sample(3)
    key0 = int(t.slot_key[0])
    t.update_priorities(np.array([key0, 10**12]), np.array([0.0, 5.0]))  # the second key never existed
    items, _ = t.sample(1_000)
    assert 0 not in set(items.tolist())
    with pytest.raises(ValueError, match="finite"):
        t.update_priorities(np.array([key0]), np.array([-1.0]))


@pytest.mark.parametrize("sampler, first", [(Fifo, 0), (Lifo, 4), (MaxHeap, 2), (MinHeap, 3)])
def test_deterministic_samplers_with_max_times_sampled_act_as_queues(sampler, first):
    t = filled(10, 5, sampler=sampler(), prios=[3, 1, 9, 0, 2], max_times_sampled=1)
    items, info = t.sample(2)
    assert items[0].item() == first
    assert t.size == 3  # each sampled item was removed after its one sample
    assert len(set(items.tolist())) == 2


def test_fifo_sampler_without_cap_returns_the_front_repeatedly():
    t = filled(10, 5, sampler=Fifo())
    items, info = t.sample(3)
    assert items.tolist() == [0, 0, 0] and t.size == 5


def test_keys_name_items_and_stale_keys_are_ignored_by_delete():
    t = filled(2, 2)
    k0 = int(t.slot_key[t.slot_key >= 0].min())
    t.insert(np.int64(2))  # removes item 0 (FIFO)
    assert t.delete(np.array([k0])) == 0
    assert t.size == 2


# ---- sum tree -------------------------------------------------------------------------
def test_sum_tree_find_matches_a_cumulative_sum():
    rng = np.random.default_rng(0)
    tree = SumTree(1_000, fanout=8)
    values = rng.random(1_000) * (rng.random(1_000) < 0.5)  # half the leaves empty
    tree.set(np.arange(1_000), values)
    u = rng.random(5_000) * values.sum()
    expected = np.searchsorted(np.cumsum(values), u, side="right")
    assert np.array_equal(tree.find(u), expected)
    assert np.isclose(tree.total, values.sum())


def test_sum_tree_repeated_indices_take_the_last_value():
    tree = SumTree(10)
    tree.set(np.array([3, 3, 5]), np.array([1.0, 4.0, 2.0]))
    assert tree.get(np.array([3]))[0] == 4.0 and np.isclose(tree.total, 6.0)


# ---- rate limiters ----------------------------------------------------------------------
def test_min_size_blocks_sampling_until_reached():
    t = filled(10, 2, limiter=MinSize(3))
    assert not t.can_sample(1)
    with pytest.raises(RateLimiterTimeout, match="sample waited"):
        t.sample(1, timeout=0.01)
    t.insert(np.int64(2))
    assert t.can_sample(100)


def test_sample_to_insert_ratio_has_reverb_bounds():
    # spi 2, min size 2, buffer 3: offset 4, diff = 2 * inserts - samples in [1, 7].
    lim = SampleToInsertRatio(2.0, 2, 3.0)
    t = filled(100, 2, limiter=lim)
    assert t.samples_available() == 3  # diff 4 - 3 = 1 >= min_diff 1
    t.sample(3)
    assert not t.can_sample(1)
    assert lim.inserts_available() == 3  # (7 + 3) / 2 - 2 = 3 more inserts
    for i in range(3):
        t.insert(np.int64(10 + i), timeout=0.01)
    with pytest.raises(RateLimiterTimeout, match="insert waited"):
        t.insert(np.int64(99), timeout=0.01)
    with pytest.raises(ValueError, match="error_buffer"):
        SampleToInsertRatio(8.0, 1, 4.0)


def test_blocked_sample_wakes_when_another_thread_inserts():
    t = Table("t", 10, rate_limiter=MinSize(2), seed=0)
    t.insert(np.int64(0))
    got = []
    reader = threading.Thread(target=lambda: got.append(t.sample(1, timeout=5.0)))
    reader.start()
    time.sleep(0.05)
    assert not got  # still blocked
    t.insert(np.int64(1))
    reader.join(timeout=5.0)
    assert got and got[0][0].item() in (0, 1)


def test_queue_hands_each_item_out_once_across_threads():
    t = Table("q", 100, Fifo(), Fifo(), Queue(10), max_times_sampled=1, seed=0)
    out: list[int] = []

    def consume():
        for _ in range(50):
            out.append(int(t.sample(1, timeout=5.0)[0][0]))

    reader = threading.Thread(target=consume)
    reader.start()
    for i in range(50):
        t.insert(np.int64(i), timeout=5.0)  # blocks whenever 10 items wait unread
    reader.join(timeout=10.0)
    assert out == list(range(50))


# ---- checkpoints ------------------------------------------------------------------------
@pytest.mark.parametrize("sampler", [Uniform, lambda: Prioritized(0.7), Fifo, MaxHeap])
def test_state_dict_round_trip_continues_identically(sampler):
    a = filled(8, 12, sampler=sampler(), prios=list(range(1, 13)))
    b = Table("t", 8, sampler(), Fifo(), MinSize(1), seed=123)
    b.load_state_dict(a.state_dict())
    for t in (a, b):
        t.insert(np.int64(100), priority=50.0)
    xa, ia = a.sample(16)
    xb, ib = b.sample(16)
    assert xa.tolist() == xb.tolist() and np.array_equal(ia.key, ib.key)
    assert contents(a) == contents(b)


def test_items_can_be_dicts_and_keep_their_structure():
    t = Table("t", 4, seed=0)
    t.insert({"obs": np.ones((2, 3), np.float32), "a": np.int64(1)})
    batch, _ = t.sample(2)
    assert batch["obs"].shape == (2, 2, 3) and batch["a"].tolist() == [1, 1]
    with pytest.raises(ValueError, match="fields"):
        t.insert({"obs": np.ones((2, 3), np.float32)})
