"""Property test: random insert / sample / update / delete sequences on a Table against a slow
reference model of Reverb's table (a dict of items plus the rate limiter's counters), for every
sampler / remover pair. After each operation: size, keys, sampled values, probabilities and the
limiter's counts agree."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from relayrl.replay import (
    Fifo,
    Lifo,
    MaxHeap,
    MinHeap,
    MinSize,
    Prioritized,
    RateLimiterTimeout,
    SampleToInsertRatio,
    Table,
    Uniform,
)

SELECTORS = {"uniform": Uniform, "prioritized": Prioritized, "fifo": Fifo, "lifo": Lifo, "minheap": MinHeap,
             "maxheap": MaxHeap}
DETERMINISTIC = {"fifo", "lifo", "minheap", "maxheap"}
PRIORITIES = [0.0, 0.5, 1.0, 2.0]  # few values: ties are common


@dataclass
class Item:
    value: int
    priority: float
    stamp: int  # the last insert or priority update, for heap ties
    times_sampled: int = 0


@dataclass
class Model:
    """Reverb's table semantics, written for clarity instead of speed."""

    max_size: int
    sampler: str
    remover: str
    exponent: float
    max_times_sampled: int
    spi: float
    min_size: int
    min_diff: float
    max_diff: float
    items: dict[int, Item] = field(default_factory=dict)  # key -> item, in insertion order
    inserts: int = 0
    samples: int = 0
    deletes: int = 0
    clock: int = 0
    max_priority: float = 1.0

    def tick(self) -> int:
        self.clock += 1
        return self.clock

    # rate limiter (reverb/cc/rate_limiter.cc)
    def can_insert(self) -> bool:
        if self.inserts + 1 - self.deletes <= self.min_size:
            return True
        return (self.inserts + 1) * self.spi - self.samples <= self.max_diff

    def can_sample(self) -> bool:
        if self.inserts - self.deletes < self.min_size or not self.items:
            return False
        return self.inserts * self.spi - self.samples - 1 >= self.min_diff

    # selectors
    def mass(self, item: Item) -> float:
        return item.priority ** self.exponent if item.priority > 0 else 0.0

    def front(self, kind: str) -> int:
        keys = list(self.items)
        if kind == "fifo":
            return keys[0]
        if kind == "lifo":
            return keys[-1]
        sign = 1.0 if kind == "minheap" else -1.0
        return min(keys, key=lambda k: (sign * self.items[k].priority, self.items[k].stamp))

    def probability(self, key: int) -> float:
        if self.sampler == "uniform":
            return 1.0 / len(self.items)
        if self.sampler == "prioritized":
            total = sum(self.mass(i) for i in self.items.values())
            return self.mass(self.items[key]) / total if total > 0 else 1.0 / len(self.items)
        return 1.0

    def valid_victims(self) -> set[int]:
        if self.remover in DETERMINISTIC:
            return {self.front(self.remover)}
        if self.remover == "prioritized" and any(self.mass(i) > 0 for i in self.items.values()):
            return {k for k, i in self.items.items() if self.mass(i) > 0}
        return set(self.items)


def live(table: Table) -> dict[int, int]:
    """key -> value of the table's live items."""
    slots = np.flatnonzero(table.slot_key >= 0)
    if slots.size == 0:
        return {}
    return dict(zip(table.slot_key[slots].tolist(), table.storage.read(slots).tolist(), strict=True))


def check(table: Table, model: Model) -> None:
    assert table.size == len(model.items)
    assert live(table) == {k: i.value for k, i in model.items.items()}
    lim = table.rate_limiter
    assert (lim.inserts, lim.samples, lim.deletes) == (model.inserts, model.samples, model.deletes)


def do_insert(table: Table, model: Model, value: int, priority: float | None) -> None:
    if not model.can_insert():
        with pytest.raises(RateLimiterTimeout):
            table.insert(np.int64(value), priority=priority, timeout=0.0)
        return
    before = dict(live(table))
    key = table.insert(np.int64(value), priority=priority, timeout=0.0)
    if len(model.items) == model.max_size:
        gone = set(before) - set(live(table))
        assert len(gone) == 1 and gone <= model.valid_victims(), (gone, model.valid_victims())
        del model.items[gone.pop()]
        model.deletes += 1
    p = model.max_priority if priority is None else priority
    if priority is not None:
        model.max_priority = max(model.max_priority, priority)
    model.items[key] = Item(value, p, model.tick())
    model.inserts += 1


def do_sample(table: Table, model: Model, n: int) -> None:
    """Items are taken one at a time while the limiter allows; a call that cannot get all n
    times out, keeping what it took (counted as samples, as Reverb counts them)."""
    expected: list[tuple[int, int]] = []
    while len(expected) < n and model.can_sample():
        if model.sampler in DETERMINISTIC:
            key = model.front(model.sampler)
            expected.append((key, model.items[key].value))
            _sampled(model, key)
        else:  # random samplers run without max_times_sampled here: nothing is deleted
            expected.append((-1, -1))
            model.samples += 1
    if len(expected) < n:
        with pytest.raises(RateLimiterTimeout):
            table.sample(n, timeout=0.0)
        return
    data, info = table.sample(n, timeout=0.0)
    values = np.asarray(data).reshape(-1).tolist()
    if model.sampler in DETERMINISTIC:
        assert info.key.tolist() == [k for k, _ in expected] and values == [v for _, v in expected]
        assert np.all(info.probability == 1.0)
        return
    for key, value, prob, prio in zip(info.key.tolist(), values, info.probability, info.priority, strict=True):
        item = model.items[key]
        assert value == item.value and prio == item.priority
        assert math.isclose(prob, model.probability(key), rel_tol=1e-9, abs_tol=1e-12)
        if model.sampler == "prioritized":  # zero priority: never sampled while anything has mass
            assert model.mass(item) > 0 or all(model.mass(i) == 0 for i in model.items.values())


def _sampled(model: Model, key: int) -> None:
    model.samples += 1
    item = model.items[key]
    item.times_sampled += 1
    if model.max_times_sampled and item.times_sampled >= model.max_times_sampled:
        del model.items[key]
        model.deletes += 1


def do_update(table: Table, model: Model, key: int, priority: float) -> None:
    table.update_priorities(np.array([key]), np.array([priority]))
    if key in model.items:
        model.items[key].priority = priority
        model.items[key].stamp = model.tick()
        model.max_priority = max(model.max_priority, priority)


def do_delete(table: Table, model: Model, key: int) -> None:
    assert table.delete(np.array([key])) == (1 if key in model.items else 0)
    if key in model.items:
        del model.items[key]
        model.deletes += 1


OPS = st.lists(st.tuples(st.sampled_from(["insert", "insert", "sample", "update", "delete"]),
                         st.integers(0, 10**6), st.sampled_from([None, *PRIORITIES]), st.integers(1, 3)),
               min_size=1, max_size=40)


@pytest.mark.parametrize("remover", sorted(SELECTORS))
@pytest.mark.parametrize("sampler", sorted(SELECTORS))
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(ops=OPS, max_size=st.integers(1, 5), exponent=st.sampled_from([0.0, 0.6, 1.0]),
       counted=st.booleans(), ratio=st.booleans())
def test_table_agrees_with_the_reference_model(sampler, remover, ops, max_size, exponent, counted, ratio):
    make = {k: (lambda c=c: c(exponent)) if k == "prioritized" else c for k, c in SELECTORS.items()}
    # max_times_sampled only with deterministic samplers, whose deletes the model can predict
    mts = 2 if counted and sampler in DETERMINISTIC else 0
    # a minimum past max_size never samples: Table refuses it
    limiter = SampleToInsertRatio(2.0, min(2, max_size), 4.0) if ratio else MinSize(1)
    table = Table("t", max_size, make[sampler](), make[remover](), limiter, max_times_sampled=mts, seed=0)
    model = Model(max_size, sampler, remover, exponent, mts, limiter.samples_per_insert,
                  limiter.min_size_to_sample, limiter.min_diff, limiter.max_diff)
    issued: list[int] = []
    for op, value, priority, n in ops:
        if op == "insert":
            do_insert(table, model, value, priority)
            issued = list(dict.fromkeys([*issued, *model.items]))
        elif op == "sample":
            do_sample(table, model, n)
        elif op == "update" and issued:
            do_update(table, model, issued[value % len(issued)], PRIORITIES[n % len(PRIORITIES)])
        elif op == "delete" and issued:
            do_delete(table, model, issued[value % len(issued)])
        check(table, model)
