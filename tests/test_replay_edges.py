"""Reverb's edge cases: heap ties, removers that must not repeat a slot, zero priorities,
max_times_sampled under the rate limiter, Stack and error_buffer ranges."""

import os

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
    Stack,
    Table,
    Uniform,
)


def live_items(t):
    live = np.flatnonzero(t.slot_key >= 0)
    return sorted(t.storage.read(live).tolist())


# ---- heaps ------------------------------------------------------------------------------
@pytest.mark.parametrize("heap", [MinHeap, MaxHeap])
@pytest.mark.parametrize("updates", [[5.0], [7.0, 5.0]], ids=["same-value", "A-B-A"])
def test_heap_remover_never_evicts_a_slot_twice(heap, updates):
    t = Table("t", 4, Uniform(), heap(), MinSize(1), seed=0)
    keys = [t.insert(np.int64(i), priority=5.0) for i in range(4)]
    for p in updates:  # item 0 ends at the priority it started with
        t.update_priorities(np.array([keys[0]]), np.array([p]))
    t.insert_batch(np.array([10, 11], dtype=np.int64))  # a full table: evicts two items
    assert t.size == 4
    assert 10 in live_items(t) and 11 in live_items(t)  # neither fresh item was lost
    assert t.rate_limiter.deletes == 2


@pytest.mark.parametrize("heap", [MinHeap, MaxHeap])
def test_heap_ties_go_to_the_least_recently_inserted_or_updated(heap):
    t = Table("t", 3, Uniform(), heap(), MinSize(1), seed=0)
    keys = [t.insert(np.int64(i), priority=1.0) for i in range(3)]
    t.update_priorities(np.array([keys[0]]), np.array([1.0]))  # item 0 is now the most recent
    t.insert(np.int64(3), priority=1.0)
    assert live_items(t) == [0, 2, 3]  # item 1 went first, then 2 would
    t.insert(np.int64(4), priority=1.0)
    assert live_items(t) == [0, 3, 4]


@pytest.mark.parametrize("heap", [MinHeap, MaxHeap])
def test_heap_sampler_ties_follow_update_order_after_a_checkpoint(heap):
    a = Table("t", 4, heap(), Fifo(), MinSize(1), seed=0)
    keys = [a.insert(np.int64(i), priority=2.0) for i in range(3)]
    a.update_priorities(np.array([keys[0]]), np.array([2.0]))
    b = Table("t", 4, heap(), Fifo(), MinSize(1), seed=0)
    b.load_state_dict(a.state_dict())
    for t in (a, b):
        assert t.sample(1)[0].item() == 1


# ---- prioritized remover and zero priorities ----------------------------------------------
def test_prioritized_remover_never_returns_a_slot_twice_when_priorities_are_zero():
    t = Table("t", 4, Uniform(), Prioritized(1.0), MinSize(1), seed=0)
    for i in range(4):
        t.insert(np.int64(i), priority=1.0 if i == 0 else 0.0)
    t.insert_batch(np.array([10, 11, 12], dtype=np.int64))
    assert t.size == 4 and [10, 11, 12] == [x for x in live_items(t) if x >= 10]
    assert t.rate_limiter.deletes == 3


@pytest.mark.parametrize("exponent", [0.0, 0.6, 1.0])
def test_a_zero_priority_is_never_sampled_for_any_exponent(exponent):
    t = Table("t", 4, Prioritized(exponent), Fifo(), MinSize(1), seed=0)
    keys = [t.insert(np.int64(i), priority=p) for i, p in enumerate([0.0, 2.0, 0.0, 3.0])]
    items, info = t.sample(2000)
    assert set(items.tolist()) == {1, 3}
    t.update_priorities(np.array([keys[1]]), np.array([0.0]))
    items, info = t.sample(200)
    assert set(items.tolist()) == {3} and np.allclose(info.probability, 1.0)


# ---- max_times_sampled under the rate limiter -----------------------------------------------
def test_max_times_sampled_checks_the_limiter_before_every_item():
    # min size 2: once sampling deletes an item below it, the limiter forbids the next one.
    t = Table("t", 10, Fifo(), Fifo(), MinSize(2), max_times_sampled=1, seed=0)
    for i in range(3):
        t.insert(np.int64(i))
    with pytest.raises(RateLimiterTimeout):
        t.sample(3, timeout=0.05)  # items 0 and 1 are allowed; the third would leave 0 items
    assert t.size == 1 and t.rate_limiter.samples == 2


@pytest.mark.parametrize("sampler", [Uniform, Fifo, lambda: Prioritized(1.0)])
def test_sampling_more_items_than_are_left_waits_and_times_out(sampler):
    t = Table("t", 10, sampler(), Fifo(), MinSize(1), max_times_sampled=1, seed=0)
    for i in range(2):
        t.insert(np.int64(i), priority=1.0)
    with pytest.raises(RateLimiterTimeout):
        t.sample(3, timeout=0.05)
    assert t.size == 0


# ---- Stack, Queue, error_buffer ranges --------------------------------------------------
def test_stack_hands_out_the_newest_item_first_and_blocks_when_full():
    t = Table("s", 10, Lifo(), Lifo(), Stack(3), max_times_sampled=1, seed=0)
    for i in range(3):
        t.insert(np.int64(i), timeout=0.01)
    with pytest.raises(RateLimiterTimeout):
        t.insert(np.int64(3), timeout=0.01)
    assert [t.sample(1)[0].item() for _ in range(3)] == [2, 1, 0]
    with pytest.raises(RateLimiterTimeout):
        t.sample(1, timeout=0.01)


def test_queue_and_stack_tables_as_reverb_builds_them():
    q, s = Table.queue("q", 5), Table.stack("s", 5)
    for t in (q, s):
        for i in range(3):
            t.insert(np.int64(i))
    assert [q.sample(1)[0].item() for _ in range(3)] == [0, 1, 2]
    assert [s.sample(1)[0].item() for _ in range(3)] == [2, 1, 0]
    assert isinstance(q.rate_limiter, Queue) and isinstance(s.rate_limiter, Stack)


def test_error_buffer_as_a_range_is_used_without_offset():
    lim = SampleToInsertRatio(2.0, 5, (-4.0, 6.0))
    assert (lim.min_diff, lim.max_diff) == (-4.0, 6.0)
    scalar = SampleToInsertRatio(2.0, 5, 5.0)  # offset 10: [5, 15]
    assert (scalar.min_diff, scalar.max_diff) == (5.0, 15.0)


@pytest.mark.parametrize("buffer, match", [
    ((0.0, 3.0), "must be >= 2"),  # narrower than 2 * max(1, samples_per_insert) = 4
    ((11.0, 20.0), "above"),  # min_diff above samples_per_insert * min_size_to_sample = 10
    ((3.0, 1.0), "must be >= 2"),
])
def test_error_buffer_ranges_that_would_deadlock_are_refused(buffer, match):
    with pytest.raises(ValueError, match=match):
        SampleToInsertRatio(2.0, 5, buffer)


# ---- refused inserts --------------------------------------------------------------------
@pytest.mark.parametrize("item, match", [
    ({"obs": np.zeros(4, np.float32), "extra": np.zeros(1)}, r"item fields \['extra', 'obs'\] differ"),
    ({"obs": np.zeros(1, np.float32)}, r"item field 'obs' has shape \(1,\) per item, the table's is \(4,\)"),
    ({"obs": np.zeros((2, 2), np.float32)}, r"item field 'obs' has shape \(2, 2\) per item, the table's is \(4,\)"),
    (np.zeros(4, np.float32), r"the table holds dicts of arrays, this item is not a dict"),
    ({"obs": np.full(4, 0.5)}, None),  # float64 into float32: same kind, taken
    ({"obs": np.array(["a", "b", "c", "d"])}, r"item field 'obs' is <U1, which the table's float32 column cannot"),
], ids=["fields", "narrow", "2-d", "not-a-dict", "float64", "text"])
def test_a_refused_insert_leaves_the_table_as_it_was(item, match):
    t = Table("t", 3, Uniform(), Fifo(), MinSize(1))
    t.insert({"obs": np.arange(4, dtype=np.float32)})
    before = (t.size, t.slot_key.copy(), t.rate_limiter.inserts)
    if match is None:
        t.insert(item)
        assert t.size == 2
        return
    with pytest.raises(ValueError, match=r"^Table 't': " + match):
        t.insert(item)
    assert (t.size, t.rate_limiter.inserts) == (before[0], before[2]) and np.array_equal(t.slot_key, before[1])
    t.insert({"obs": np.ones(4, np.float32)})  # the slot a refused insert would have taken is free
    t.insert({"obs": np.ones(4, np.float32)})
    assert t.size == 3
    assert sorted(t.storage.read(np.flatnonzero(t.slot_key >= 0))["obs"].sum(1).tolist()) == [4.0, 4.0, 6.0]


def test_a_refused_insert_of_single_arrays_leaves_the_table_as_it_was():
    t = Table("t", 2, Uniform(), Fifo(), MinSize(1))
    t.insert_batch(np.zeros((2, 3), np.int64))
    with pytest.raises(ValueError, match=r"^Table 't': item field 'item' is float64, which the table's int64 column"):
        t.insert_batch(np.full((2, 3), 0.5))  # 0.5 would be stored as 0
    with pytest.raises(ValueError, match=r"^Table 't': the table holds single arrays, this item is a dict"):
        t.insert({"x": np.zeros(3)})
    assert t.size == 2 and t.rate_limiter.inserts == 2


@pytest.mark.skipif(not os.path.exists("/proc/sys/vm/overcommit_memory")
                    or open("/proc/sys/vm/overcommit_memory").read().strip() == "2",
                    reason="Linux with its default overcommit policy")
def test_a_host_table_larger_than_the_machine_is_made_and_takes_memory_as_rows_are_written():
    """SAC's 1M-row default replay of 100x100 images (29.7 GiB) was refused for a 1,000-step run on
    a 16 GB machine: np.zeros asks for it all at once."""
    from relayrl.replay.storage import Columns

    twice = 2 * os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    cols = Columns({"frame": ((100, 100, 3), np.uint8)}, (twice // 30_000,))
    frames = cols.arrays["frame"]
    frames[:1000] = 7
    assert frames.nbytes >= twice - 30_000 and frames[999, 0, 0, 0] == 7 and frames[1000, 0, 0, 0] == 0
    assert cols.state_dict(used=1000)["arrays"]["frame"].sum() == 7 * 1000 * 30_000
