"""Table semantics: selectors as samplers and removers, rate limiters, keys, checkpoints."""

import threading
import time

import numpy as np
import pytest
from tree_checks import check_updates_and_finds

from relayrl.compile import numba_available
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
from relayrl.replay.selectors import make_sum_tree
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


def test_without_numba_prioritized_tables_use_the_numpy_tree(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "numba", None)  # its import now fails
    assert type(make_sum_tree(10)[0]) is SumTree
    t = filled(3, 3, sampler=Prioritized(1.0), prios=[1.0, 0.0, 3.0])
    assert type(t.sampler.tree) is SumTree and set(t.sample(50)[1].priority.tolist()) == {1.0, 3.0}


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


# ---- fast paths against the general ones -----------------------------------------------------
@pytest.mark.parametrize("remover", [Fifo, Lifo, MinHeap, MaxHeap, Uniform])
@pytest.mark.parametrize("sampler", [Uniform, lambda: Prioritized(0.5)])
def test_inserting_one_item_on_the_scalar_path_matches_the_array_path(remover, sampler):
    # One item takes a scalar path; force the array path on a twin table and compare keys,
    # slots, priorities and what both sample, also once each insert removes an item.
    rng = np.random.default_rng(0)
    prios = rng.uniform(0.1, 5.0, 40)
    a, b = (Table("t", 8, sampler(), remover(), MinSize(1), seed=0) for _ in range(2))
    b._insert_one_locked = lambda items, p: b._insert_many_locked(items, p, 1)
    for i in range(40):
        assert a.insert(np.int64(i), priority=prios[i]) == b.insert(np.int64(i), priority=prios[i])
        if i % 7 == 6:  # deletes leave holes the next inserts fill
            assert a.delete(a.slot_key[[i % 8]]) == b.delete(b.slot_key[[i % 8]])
    assert np.array_equal(a.slot_key, b.slot_key) and np.array_equal(a.priority, b.priority)
    assert contents(a) == contents(b)
    xa, ia = a.sample(64)
    xb, ib = b.sample(64)
    assert xa.tolist() == xb.tolist() and np.array_equal(ia.probability, ib.probability)


@pytest.mark.parametrize("stale_keys", [False, True])
def test_compiled_insert_leaves_the_numpy_paths_table(stale_keys):
    # relayrl[fast]: a Uniform/Fifo table inserts n > 1 items in numba loops (table_fast): free
    # slots, then the Fifo's oldest live items as victims. Twin tables, one forced onto the
    # NumPy path, through inserts that fit, that overflow (victims), deletes (stale keys the
    # victim search must skip) and samples.
    if not numba_available():
        pytest.skip("the compiled insert needs numba (pip install relayrl[fast]) and RELAYRL_NUMBA not 0")
    rng = np.random.default_rng(3)
    a, b = (Table("t", 60, Uniform(), Fifo(), MinSize(1), seed=0, fast=fast) for fast in (True, False))
    assert a._insert_kernel is not None and b._insert_kernel is None
    free_only = with_victims = 0
    for step in range(120):
        n = int(rng.integers(2, 30))
        free_only += n <= a._num_free
        with_victims += n > a._num_free
        items = np.arange(step * 100, step * 100 + n)
        assert a.insert_batch(items, n=n).tolist() == b.insert_batch(items, n=n).tolist()
        if rng.random() < (0.5 if stale_keys else 0.1) and a.size:
            gone = rng.choice(a.slot_key[a.slot_key >= 0], size=min(a.size, int(rng.integers(1, 40))), replace=False)
            assert a.delete(gone) == b.delete(gone)
        if rng.random() < 0.3:
            assert a.sample(5)[0].tolist() == b.sample(5)[0].tolist()
        for name in ("slot_key", "priority", "times_sampled"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
        sa, sb, ra, rb = a.sampler, b.sampler, a.remover, b.remover
        assert (sa.size, sa.identity, ra.size, a._num_free, a._inserted) == (sb.size, sb.identity, rb.size,
                                                                            b._num_free, b._inserted)
        assert np.array_equal(sa.dense[:sa.size], sb.dense[:sb.size])
        live = np.flatnonzero(a.slot_key >= 0)
        assert np.array_equal(sa.where[live], sb.where[live])
        qa, qb = ra.queue[ra.head:ra.tail], rb.queue[rb.head:rb.tail]  # live keys in the same order
        assert np.array_equal(qa[a.slot_key[qa % 60] == qa], qb[b.slot_key[qb % 60] == qb])
        assert contents(a) == contents(b)
        assert a.rate_limiter.state_dict() == b.rate_limiter.state_dict()
    assert free_only >= 10 and with_victims >= 20


def test_without_numba_tables_insert_in_numpy(monkeypatch):
    assert Table("t", 10, Uniform(), Lifo(), MinSize(1))._insert_kernel is None  # only Uniform/Fifo compile
    monkeypatch.setenv("RELAYRL_NUMBA", "0")
    assert Table("t", 10, Uniform(), Fifo(), MinSize(1))._insert_kernel is None


@pytest.mark.parametrize("queue", [Fifo, Lifo])
def test_queue_removers_skip_deleted_items_like_a_deque(queue):
    # The queue is a NumPy array popped in batches; check it against a plain list model.
    rng = np.random.default_rng(1)
    t = Table("t", 50, Uniform(), queue(), MinSize(1), seed=0)
    model: list[int] = []  # live keys, oldest first
    for _ in range(60):
        n = int(rng.integers(1, 30))
        full = max(0, len(model) + n - 50)
        removed = (model[:full] if queue is Fifo else model[::-1][:full]) if full else []
        keys = t.insert_batch(np.arange(n), n=n).tolist()
        model = [k for k in model if k not in removed] + keys
        if rng.random() < 0.5 and model:
            gone = rng.choice(model, size=min(len(model), int(rng.integers(1, 10))), replace=False).tolist()
            assert t.delete(np.array(gone)) == len(gone)
            model = [k for k in model if k not in gone]
        assert sorted(model) == sorted(t.slot_key[t.slot_key >= 0].tolist())
        assert t.sampler.size == t.remover.size == len(model)


def test_uniform_sampling_skips_the_dense_list_only_while_it_is_the_identity():
    t = filled(10, 25)  # filled in order and refilled by FIFO: dense[:size] is arange(size)
    assert t.sampler.identity
    t.delete(t.slot_key[[2, 7]])
    assert not t.sampler.identity
    items, info = t.sample(2_000)
    assert set((info.key % 10).tolist()) == set(np.flatnonzero(t.slot_key >= 0).tolist())
    assert all(t.storage.read(np.array([k % 10]))[0] == x for k, x in zip(info.key, items.tolist(), strict=True))
    b = Table("t", 10, Uniform(), Fifo(), MinSize(1), seed=0)
    b.load_state_dict(t.state_dict())
    assert not b.sampler.identity and b.sample(50)[0].tolist() == t.sample(50)[0].tolist()


@pytest.mark.parametrize("top_size", [4, 40, 32768])  # two grouped levels, one, none
def test_sum_tree_levels_find_what_a_flat_cumulative_sum_finds(top_size):
    check_updates_and_finds(SumTree(5_000, fanout=8, top_size=top_size), 5_000, seed=2)


def test_sum_tree_moves_a_query_off_an_empty_leaf():
    tree = SumTree(100, fanout=4, top_size=4)
    tree.set(np.array([10, 50]), np.array([1.0, 2.0]))
    node, mass = tree._nonempty(np.array([10, 30, 5, 70]), tree.get(np.array([10, 30, 5, 70])))
    assert node.tolist() == [10, 10, 10, 50] and mass.tolist() == [1.0, 1.0, 1.0, 2.0]


def test_inserts_that_would_wait_go_through_when_inserts_do_not_wait():
    # The one-process loop's table: its thread cannot sample while an insert waits.
    t = Table("t", 100, rate_limiter=SampleToInsertRatio(2.0, min_size_to_sample=4, error_buffer=4.0), seed=0)
    t.inserts_wait = False
    t.insert_batch(np.zeros((20, 1)))  # 16 items past what the limiter allows before a sample
    lim = t.rate_limiter
    assert t.size == 20 and lim.inserts_available() == 0
    assert t.samples_available() == 20 * 2 - lim.min_diff  # the samples that restore the ratio
    t.inserts_wait = True
    with pytest.raises(RateLimiterTimeout):
        t.insert_batch(np.zeros((1, 1)), timeout=0.01)


def test_a_selector_serves_one_table_and_a_minimum_past_the_capacity_is_refused():
    from relayrl.replay import MinSize, Table, Uniform

    shared = Uniform()
    Table("a", 8, sampler=shared)
    with pytest.raises(ValueError, match=r"^this Uniform already selects for another table: give each table its own"):
        Table("b", 8, sampler=shared)  # both tables' samples went wrong
    with pytest.raises(ValueError, match=r"^Table 'c': its rate limiter waits for 1,000 items before sampling, more "
                                        r"than max_size=100 holds"):
        Table("c", 100, rate_limiter=MinSize(1000))  # sampling would wait forever
