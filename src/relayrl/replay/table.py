"""Table: Reverb's replay table (sampler, remover, max size, rate limiter) in one process.

Items live in slots [0, max_size). A key is `insert_count * max_size + slot`, so a key
names its slot and a stale key (its slot since reused) is recognised in O(1). Every public
method holds one lock, so actors and learners in different threads can share a table;
`insert` and `sample` block on the rate limiter, with an optional timeout.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

from relayrl.compile import numba_available
from relayrl.replay.rate_limiters import MinSize, Queue, RateLimiter, Stack
from relayrl.replay.selectors import Fifo, Lifo, Selector, Uniform
from relayrl.replay.step_storage import StepStorage
from relayrl.replay.steps import StepChunk
from relayrl.replay.storage import ItemStorage, Storage


class RateLimiterTimeout(TimeoutError):
    """An insert or sample waited longer than its timeout for the rate limiter."""


class SampleInfo(NamedTuple):
    key: np.ndarray  # [N] int64
    probability: np.ndarray  # [N] float64, the chance this item had of being sampled
    table_size: int
    priority: np.ndarray  # [N] float64


class Table:
    def __init__(self, name: str, max_size: int, sampler: Selector | None = None, remover: Selector | None = None,
                 rate_limiter: RateLimiter | None = None, max_times_sampled: int = 0,
                 seed: int | np.random.SeedSequence | None = None, fast: bool = True) -> None:
        if max_size < 1:
            raise ValueError(f"Table {name!r}: max_size={max_size} is not valid; it must be >= 1")
        sampler = sampler if sampler is not None else Uniform()
        remover = remover if remover is not None else Fifo()
        if sampler is remover:
            raise ValueError(f"Table {name!r}: sampler and remover must be separate selector objects")
        self.name = name
        self.max_size = max_size
        self.sampler = sampler
        self.remover = remover
        self.rate_limiter = rate_limiter if rate_limiter is not None else MinSize(1)
        if self.rate_limiter.min_size_to_sample > max_size:  # sampling would wait forever
            raise ValueError(f"Table {name!r}: its rate limiter waits for {self.rate_limiter.min_size_to_sample:,} "
                             f"items before sampling, more than max_size={max_size:,} holds")
        self.max_times_sampled = max_times_sampled
        self.rng = np.random.default_rng(seed)
        self.slot_key = np.full(max_size, -1, dtype=np.int64)
        self.priority = np.zeros(max_size, dtype=np.float64)
        self.times_sampled = np.zeros(max_size, dtype=np.int32)
        self.max_priority = 1.0  # given to items inserted without a priority
        self._free = np.arange(max_size - 1, -1, -1, dtype=np.int64)  # a stack; pop from the end
        self._num_free = max_size
        self._inserted = 0
        self._cv = threading.Condition()
        self._waiting = 0  # threads blocked on the rate limiter: only then does a write need notify_all()
        # False: inserts never wait on the rate limiter (samples still do). For one thread that
        # both inserts and samples (the one-process loop): it cannot sample while its insert
        # waits, and the samples it then takes (`samples_available`) restore the ratio anyway.
        self.inserts_wait = True
        for selector in (sampler, remover):
            selector.bind(max_size, self.slot_key, self.priority)
        # A compiled prioritized sampler updates keys in one pass, when the remover has no
        # use for priorities (Fifo, Lifo, Uniform); otherwise both are told in NumPy.
        one_pass = sampler.update_keys if type(remover).update is Selector.update else None
        self._update_keys: Callable[[np.ndarray, np.ndarray], float] = one_pass or self._update_slots
        # `fast`: inserts of n > 1 items in compiled loops (table_fast) for the usual pair of
        # selectors, when numba is there; else (and with fast=False) the NumPy path.
        self._insert_kernel: Callable[..., tuple[int, bool]] | None = None
        if fast and type(sampler) is Uniform and type(remover) is Fifo and numba_available():
            from relayrl.replay.table_fast import insert
            self._insert_kernel = insert
        self.storage: Storage = ItemStorage(max_size)
        self.storage.bind(self.slot_key)

    def set_storage(self, storage: Storage) -> None:
        """Keep items in `storage` from now on; only before the first insert. A writer hands
        its table a step storage (see step_storage) when it is built."""
        with self._cv:
            if self._inserted:
                raise ValueError(f"Table {self.name!r} already took items; its storage is set before the first insert")
            self.storage = storage
            storage.bind(self.slot_key)

    @classmethod
    def queue(cls, name: str, max_size: int) -> Table:
        """Reverb's `Table.queue`: every item sampled once, oldest first; inserts block while
        `max_size` items wait, samples while none does."""
        return cls(name, max_size, Fifo(), Fifo(), Queue(max_size), max_times_sampled=1)

    @classmethod
    def stack(cls, name: str, max_size: int) -> Table:
        """Reverb's `Table.stack`: as `queue`, newest item first."""
        return cls(name, max_size, Lifo(), Lifo(), Stack(max_size), max_times_sampled=1)

    # ---- introspection ------------------------------------------------------------------
    @property
    def size(self) -> int:
        return self.max_size - self._num_free

    def __len__(self) -> int:
        return self.size

    # Under the lock: the size and the limiter's counters are read as one state, never between
    # an insert's slot bookkeeping and its limiter update on another thread.
    def can_sample(self, n: int = 1) -> bool:
        with self._cv:
            return self.size > 0 and self.rate_limiter.can_sample(n)

    def samples_available(self) -> int:
        with self._cv:
            return self.rate_limiter.samples_available() if self.size > 0 else 0

    def __repr__(self) -> str:
        with self._cv:
            return (f"Table(name={self.name!r}, max_size={self.max_size}, sampler={self.sampler!r}, "
                    f"remover={self.remover!r}, rate_limiter={self.rate_limiter!r}, size={self.size})")

    # ---- writes ---------------------------------------------------------------------
    def insert(self, item: Any, priority: float | None = None, timeout: float | None = None) -> int:
        """Insert one item (a dict of arrays, or an array); returns its key."""
        items = {k: _unsqueeze(v) for k, v in item.items()} if isinstance(item, dict) else _unsqueeze(item)
        prio = None if priority is None else np.array([priority], dtype=np.float64)
        return int(self.insert_batch(items, prio, timeout=timeout)[0])

    def insert_batch(self, items: Any, priorities: np.ndarray | None = None, n: int | None = None,
                     timeout: float | None = None) -> np.ndarray:
        """Insert n items given with a leading batch dimension; returns their keys."""
        if n is None:
            first = next(iter(items.values())) if isinstance(items, dict) else items
            n = len(first)
        if priorities is not None:
            priorities = np.asarray(priorities, dtype=np.float64).reshape(-1)
            if priorities.size != n or not _valid_priorities(priorities):
                raise ValueError(f"Table {self.name!r}: need {n} finite priorities >= 0")
        try:
            self.storage.check(items, n)
        except ValueError as e:
            raise ValueError(f"Table {self.name!r}: {e}") from None
        with self._cv:
            if n <= self.max_size and (not self.inserts_wait or self.rate_limiter.inserts_available() >= n):
                keys = self._insert_locked(items, priorities, n)  # the usual case: no split, no wait
            else:
                keys = self._insert_parts(items, priorities, n, timeout)
            if self._waiting:
                self._cv.notify_all()
        return keys

    def _insert_parts(self, items: Any, priorities: np.ndarray | None, n: int, timeout: float | None) -> np.ndarray:
        """Insert in as many parts as the rate limiter and max_size allow, waiting in between."""
        keys = np.empty(n, dtype=np.int64)
        done = 0
        while done < n:
            allowed = self._wait(self.rate_limiter.inserts_available, timeout, "insert") if self.inserts_wait else n
            k = min(n - done, allowed, self.max_size)
            part = slice(done, done + k)
            sub = items if (done == 0 and k == n) else _slice(items, part)
            keys[part] = self._insert_locked(sub, None if priorities is None else priorities[part], k)
            done += k
            if self._waiting:
                self._cv.notify_all()  # a sampler may be waiting for what was just inserted
        return keys

    def _insert_locked(self, items: Any, priorities: np.ndarray | None, n: int) -> np.ndarray:
        if n == 1:
            return self._insert_one_locked(items, priorities)
        if self._insert_kernel is not None and priorities is None:
            return self._insert_compiled(items, n)
        return self._insert_many_locked(items, priorities, n)

    def _insert_many_locked(self, items: Any, priorities: np.ndarray | None, n: int) -> np.ndarray:
        n_free = min(n, self._num_free)
        free = self._free[self._num_free - n_free:self._num_free][::-1].copy()
        self._num_free -= n_free
        victims = self.remover.pop(n - n_free, self.rng) if n > n_free else np.zeros(0, dtype=np.int64)
        slots = np.concatenate([free, victims]) if victims.size else free
        keys = np.arange(self._inserted, self._inserted + n, dtype=np.int64)
        keys *= self.max_size
        keys += slots
        self._inserted += n
        self.slot_key[slots] = keys
        if priorities is None:
            self.priority[slots] = self.max_priority
        else:
            self.priority[slots] = priorities
            self.max_priority = max(self.max_priority, float(priorities.max()))
        self.times_sampled[slots] = 0
        self.storage.write(slots, items)
        for selector in (self.sampler, self.remover):
            if n_free:
                selector.insert(free, keys[:n_free])
            if victims.size:
                selector.replace(victims, keys[n_free:])
        limiter = self.rate_limiter
        limiter.inserts += n
        limiter.deletes += victims.size
        return keys

    def _insert_compiled(self, items: Any, n: int) -> np.ndarray:
        """`_insert_many_locked` for a Uniform sampler and a Fifo remover, no priorities given, in
        compiled loops (table_fast)."""
        sampler, remover = self.sampler, self.remover
        assert isinstance(sampler, Uniform) and isinstance(remover, Fifo) and self._insert_kernel is not None
        remover.reserve(n)
        slots = np.empty(n, dtype=np.int64)
        keys = np.empty(n, dtype=np.int64)
        head, sampler.identity = self._insert_kernel(
            slots, keys, self._free, self._num_free, self._inserted, self.slot_key, self.priority, self.max_priority,
            self.times_sampled, sampler.dense, sampler.where, sampler.size, sampler.identity, remover.queue,
            remover.head, remover.tail)
        if head < 0:
            raise IndexError("pop from an empty queue")  # as _KeyQueue.pop
        remover.head = head
        n_free = min(n, self._num_free)
        self._num_free -= n_free
        self._inserted += n
        sampler.size += n_free
        remover.tail += n
        remover.size += n_free  # a victim's delete and its slot's insert cancel out
        self.rate_limiter.inserts += n
        self.rate_limiter.deletes += n - n_free
        if n > n_free:
            remover.trim()  # as its delete of the victims would
        self.storage.write(slots, items)
        return keys

    def _insert_one_locked(self, items: Any, priorities: np.ndarray | None) -> np.ndarray:
        """`_insert_many_locked` for one item, in Python scalars: a one-env writer inserts one item
        per step, and the NumPy path's dozen array calls on one-element arrays cost several
        times this (a prioritized table has no compiled insert)."""
        if self._num_free:
            self._num_free -= 1
            slot = int(self._free[self._num_free])
            victim = False
        else:
            slot = int(self.remover.pop(1, self.rng)[0])
            victim = True
        key = self._inserted * self.max_size + slot
        self._inserted += 1
        self.slot_key[slot] = key
        if priorities is None:
            self.priority[slot] = self.max_priority
        else:
            p = float(priorities[0])
            self.priority[slot] = p
            self.max_priority = max(self.max_priority, p)
        self.times_sampled[slot] = 0
        slots, keys = np.array([slot]), np.array([key])
        self.storage.write(slots, items)
        for selector in (self.sampler, self.remover):
            (selector.replace if victim else selector.insert)(slots, keys)
        self.rate_limiter.inserts += 1
        self.rate_limiter.deletes += victim
        return keys

    # ---- steps (a table whose storage holds steps and makes items of them) -------------------
    def append_steps(self, chunk: StepChunk) -> None:
        """Delete the items whose rows these steps overwrite, append them to the step storage
        (outside the lock: no live item reads those rows now), and insert the items they close."""
        steps = self._steps()
        self._append(steps.evictions(chunk.done), lambda: steps.append(chunk))

    def append_step(self, frames: Any, actions: Any, rewards: Any) -> bool:
        """`append_steps` of one batched step without episode ends ([B, ...] each) on the step
        storage's compiled path; False, with nothing written, where it has none."""
        one_step = self._steps().one_step
        if one_step is None:
            return False
        self._append(one_step.evictions(), lambda: one_step.append(frames, actions, rewards))
        return True

    def _append(self, evicted: np.ndarray, append: Callable[[], np.ndarray]) -> None:
        if evicted.size:
            self.delete(evicted)
        items = append()
        if len(items):
            self.insert_batch(items, n=len(items))

    def _steps(self) -> StepStorage:
        if (steps := self.storage.appending) is None:
            raise TypeError(f"Table {self.name!r} keeps items, not steps: give it a writer before appending steps")
        return steps

    def update_priorities(self, keys: np.ndarray, priorities: np.ndarray) -> None:
        """Set new priorities; keys of items no longer in the table are ignored (as in Reverb)."""
        keys = np.asarray(keys, dtype=np.int64).reshape(-1)
        priorities = np.asarray(priorities, dtype=np.float64).reshape(-1)
        if priorities.size != keys.size:
            raise ValueError(f"Table {self.name!r}: {keys.size} keys but {priorities.size} priorities")
        if priorities.size == 0:
            return
        with self._cv:
            try:
                top = self._update_keys(keys, priorities)
            except ValueError:
                raise ValueError(f"Table {self.name!r}: priorities must be finite and >= 0") from None
            if top >= 0.0:
                self.max_priority = max(self.max_priority, top)

    def _update_slots(self, keys: np.ndarray, priorities: np.ndarray) -> float:
        """update_priorities in NumPy, telling both selectors; returns the largest priority
        written (-1.0: no key was live)."""
        if not _valid_priorities(priorities):
            raise ValueError("priorities must be finite and >= 0")
        slots = keys % self.max_size
        live = (self.slot_key.take(slots) == keys) & (keys >= 0)  # key -1 would match an empty slot
        if np.count_nonzero(live) < live.size:
            slots, priorities = slots[live], priorities[live]
            if slots.size == 0:
                return -1.0
        self.priority[slots] = priorities
        self.sampler.update(slots)
        self.remover.update(slots)
        return float(priorities.max())

    def delete(self, keys: np.ndarray) -> int:
        """Remove items by key; returns how many were still in the table (keys of items gone
        already, or never inserted, are ignored)."""
        keys = np.asarray(keys, dtype=np.int64).reshape(-1)
        slots = keys % self.max_size
        # A key that is not live now never is again (keys are never reused), so a call whose
        # keys are all gone (a writer's usual eviction) returns without taking the lock.
        if not (self.slot_key.take(slots) == keys).any():
            return 0
        with self._cv:
            slots = np.unique(slots[(self.slot_key[slots] == keys) & (keys >= 0)])  # key -1 matches an empty slot
            if slots.size:
                self._delete_slots(slots)
                if self._waiting:
                    self._cv.notify_all()
            return int(slots.size)

    def _delete_slots(self, slots: np.ndarray) -> None:
        self.sampler.delete(slots)
        self.remover.delete(slots)
        self.slot_key[slots] = -1
        self._free[self._num_free:self._num_free + slots.size] = slots
        self._num_free += slots.size
        self.rate_limiter.deletes += slots.size

    # ---- reads ----------------------------------------------------------------------
    def sample(self, batch_size: int, timeout: float | None = None) -> tuple[Any, SampleInfo]:
        """Sample `batch_size` items (with replacement), blocking on the rate limiter."""
        if batch_size < 1:
            raise ValueError(f"batch_size={batch_size} is not valid; it must be >= 1")
        with self._cv:
            if self.max_times_sampled == 0 and self.samples_available() >= batch_size:
                out = self._sample_locked(batch_size)  # the usual case: one part, no wait
            else:
                out = self._sample_parts(batch_size, timeout)
            if self._waiting:
                self._cv.notify_all()
        return out

    def _sample_parts(self, batch_size: int, timeout: float | None) -> tuple[Any, SampleInfo]:
        parts: list[tuple[Any, SampleInfo]] = []
        got = 0
        while got < batch_size:
            allowed = self._wait(self.samples_available, timeout, "sample")
            # With max_times_sampled, each item sampled may delete one and so change what the
            # limiter allows: ask it again before every item, as Reverb does.
            k = 1 if self.max_times_sampled > 0 else min(batch_size - got, allowed)
            parts.append(self._sample_locked(k))
            got += k
            if self._waiting:
                self._cv.notify_all()  # an inserter may be waiting for these samples
        if len(parts) == 1:
            return parts[0]
        infos = [i for _, i in parts]
        info = SampleInfo(np.concatenate([i.key for i in infos]), np.concatenate([i.probability for i in infos]),
                          infos[-1].table_size, np.concatenate([i.priority for i in infos]))
        return _concat([d for d, _ in parts]), info

    def _sample_locked(self, n: int) -> tuple[Any, SampleInfo]:
        if self.max_times_sampled > 0:
            return self._sample_counted(n)
        slots, probs, keys, prios = self.sampler.select_items(n, self.rng)
        self.rate_limiter.samples += n
        return self.storage.read(slots), SampleInfo(keys, probs, self.size, prios)

    def _sample_counted(self, n: int) -> tuple[Any, SampleInfo]:
        # One item at a time, so an item is never handed out more often than max_times_sampled,
        # even within one batch (the caller checked the rate limiter for each).
        slots = np.empty(n, dtype=np.int64)
        probs = np.empty(n)
        keys = np.empty(n, dtype=np.int64)
        prios = np.empty(n)
        data = []
        for i in range(n):
            (slot,), (prob,) = self.sampler.select(1, self.rng)
            slots[i], probs[i], keys[i], prios[i] = slot, prob, self.slot_key[slot], self.priority[slot]
            data.append(self.storage.read(np.array([slot])))  # read before the slot can be reused
            self.times_sampled[slot] += 1
            self.rate_limiter.samples += 1
            if self.times_sampled[slot] >= self.max_times_sampled:
                self._delete_slots(np.array([slot]))
        return (_concat(data) if n > 1 else data[0]), SampleInfo(keys, probs, self.size, prios)

    def _wait(self, available: Callable[[], int], timeout: float | None, what: str) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            allowed = available()
            if allowed > 0:
                return allowed
            remaining = None if deadline is None else deadline - time.monotonic()
            if remaining is not None and remaining <= 0:
                lim = self.rate_limiter
                raise RateLimiterTimeout(
                    f"table {self.name!r}: {what} waited {timeout}s for the rate limiter "
                    f"(size {self.size}, inserts {lim.inserts}, samples {lim.samples}, {lim!r}); "
                    f"nothing is {'sampling' if what == 'insert' else 'inserting'} fast enough")
            self._waiting += 1
            try:
                self._cv.wait(remaining)
            finally:
                self._waiting -= 1

    # ---- checkpoints ----------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        with self._cv:
            live = np.flatnonzero(self.slot_key >= 0)
            live = live[np.argsort(self.slot_key[live], kind="stable")]  # key order = insertion order
            return {
                "name": self.name, "max_size": self.max_size, "live": live,
                "slot_key": self.slot_key[live].copy(), "priority": self.priority[live].copy(),
                "times_sampled": self.times_sampled[live].copy(), "max_priority": self.max_priority,
                "inserted": self._inserted, "rng": self.rng.bit_generator.state,
                "rate_limiter": self.rate_limiter.state_dict(),
                "sampler": self.sampler.state_dict(), "remover": self.remover.state_dict(),
                "storage": self.storage.state_dict(),
            }

    def load_state_dict(self, state: dict[str, Any]) -> int:
        """Load `state_dict`'s state; returns how many of its items were dropped (0 but where a
        memmap storage's rows were written after the state was taken)."""
        if int(state["max_size"]) != self.max_size:
            raise ValueError(f"checkpointed table {state['name']!r} has max_size {state['max_size']}, "
                             f"this table {self.max_size}")
        with self._cv:
            self.storage.load_state_dict(state["storage"])
            live = np.asarray(state["live"], dtype=np.int64)
            self.slot_key[:] = -1
            self.slot_key[live] = state["slot_key"]
            self.priority[:] = 0.0
            self.priority[live] = state["priority"]
            self.times_sampled[:] = 0
            self.times_sampled[live] = state["times_sampled"]
            free = np.setdiff1d(np.arange(self.max_size), live)[::-1]
            self._num_free = free.size
            self._free[: free.size] = free
            self.max_priority = float(state["max_priority"])
            self._inserted = int(state["inserted"])
            self.rng.bit_generator.state = state["rng"]
            self.rate_limiter.load_state_dict(state["rate_limiter"])
            self.sampler.load_state_dict(state["sampler"], live)
            self.remover.load_state_dict(state["remover"], live)
            if live.size:
                # Memmap rows written after this checkpoint no longer hold what these items read.
                gone = live[self.storage.stale(live)]
                if gone.size:
                    self._delete_slots(gone)
                return int(gone.size)
            return 0


def _valid_priorities(p: np.ndarray) -> bool:
    """All finite and >= 0 (a NaN fails both comparisons), in two reductions."""
    return p.size == 0 or bool(p.min() >= 0.0 and p.max() < np.inf)


def _unsqueeze(x: Any) -> Any:
    return np.asarray(x)[None] if not hasattr(x, "unsqueeze") else x.unsqueeze(0)


def _slice(items: Any, part: slice) -> Any:
    if isinstance(items, dict):
        return {k: v[part] for k, v in items.items()}
    return items[part]


def _concat(datas: list[Any]) -> Any:
    """Samples read in parts as one batch: a dict or a NamedTuple (fields None stay None) of tensors, or a tensor."""
    import torch

    first = datas[0]
    if isinstance(first, dict):
        return {k: torch.cat([d[k] for d in datas]) for k in first}
    if hasattr(first, "_fields"):
        return type(first)(*(None if f[0] is None else torch.cat(f) for f in zip(*datas, strict=True)))
    return torch.cat(datas)
