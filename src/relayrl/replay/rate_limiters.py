"""Rate limiters with Reverb's semantics.

A limiter counts inserts, samples (items, not batches) and deletes, and allows an insert
or a sample only while `inserts * samples_per_insert - samples` stays within
[min_diff, max_diff] (`reverb/cc/rate_limiter.cc`). Inserts are always allowed until the
table holds `min_size_to_sample` items; samples never before. The Table blocks callers on
the limiter; the local trainer instead asks `samples_available()` so that one process
takes exactly the gradient steps the same limiter would let a remote learner take.
"""

from __future__ import annotations

import math
from typing import Any

UNLIMITED = 2**62  # samples or inserts a limiter without a rate (MinSize) allows: any number


class RateLimiter:
    def __init__(self, samples_per_insert: float, min_size_to_sample: int,
                 min_diff: float, max_diff: float) -> None:
        if min_size_to_sample < 1:
            raise ValueError(f"min_size_to_sample={min_size_to_sample} is not valid; it must be >= 1")
        if samples_per_insert <= 0:
            raise ValueError(f"samples_per_insert={samples_per_insert} is not valid; it must be > 0")
        if min_diff > max_diff:
            raise ValueError(f"min_diff={min_diff} > max_diff={max_diff}: nothing could ever be sampled")
        self.samples_per_insert = float(samples_per_insert)
        self.min_size_to_sample = int(min_size_to_sample)
        self.min_diff = float(min_diff)
        self.max_diff = float(max_diff)
        self.inserts = 0
        self.samples = 0
        self.deletes = 0

    def can_sample(self, n: int = 1) -> bool:
        if self.inserts - self.deletes < self.min_size_to_sample:
            return False
        return self.inserts * self.samples_per_insert - self.samples - n >= self.min_diff

    def samples_available(self) -> int:
        """How many items could be sampled now without blocking (no inserts in between)."""
        if self.inserts - self.deletes < self.min_size_to_sample:
            return 0
        room = self.inserts * self.samples_per_insert - self.samples - self.min_diff
        return max(0, math.floor(room + 1e-9)) if math.isfinite(room) else UNLIMITED

    def inserts_available(self) -> int:
        """How many items could be inserted now without blocking (no samples in between)."""
        free = max(0, self.min_size_to_sample - (self.inserts - self.deletes))
        room = (self.max_diff + self.samples) / self.samples_per_insert - self.inserts
        if not math.isfinite(room):
            return UNLIMITED
        return max(free, math.floor(room + 1e-9))

    def state_dict(self) -> dict[str, Any]:
        return {"inserts": self.inserts, "samples": self.samples, "deletes": self.deletes}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.inserts = int(state["inserts"])
        self.samples = int(state["samples"])
        self.deletes = int(state["deletes"])

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(samples_per_insert={self.samples_per_insert}, "
                f"min_size_to_sample={self.min_size_to_sample}, min_diff={self.min_diff}, "
                f"max_diff={self.max_diff})")


class MinSize(RateLimiter):
    """Block sampling until the table holds `min_size_to_sample` items; never block inserts."""

    def __init__(self, min_size_to_sample: int) -> None:
        super().__init__(1.0, min_size_to_sample, -math.inf, math.inf)


class SampleToInsertRatio(RateLimiter):
    """Keep samples per insert near `samples_per_insert`, within `error_buffer` samples.

    Reverb's definition: a number `error_buffer` is a range around the offset
    `samples_per_insert * min_size_to_sample`, so `inserts * samples_per_insert - samples`
    stays in offset +- error_buffer; a pair `(min_diff, max_diff)` is that range itself, with
    no offset. The range must be at least 2 * max(1, samples_per_insert) wide, or inserts and
    samples could block each other forever, and must not start above the offset, or sampling
    would block as soon as the table reaches its minimum size.
    """

    def __init__(self, samples_per_insert: float, min_size_to_sample: int,
                 error_buffer: float | tuple[float, float]) -> None:
        offset = samples_per_insert * min_size_to_sample
        if isinstance(error_buffer, tuple | list):
            min_diff, max_diff = (float(x) for x in error_buffer)
        else:
            min_diff, max_diff = offset - error_buffer, offset + error_buffer
        if max_diff - min_diff < 2 * max(1.0, samples_per_insert):
            raise ValueError(f"error_buffer={error_buffer} is too small: the range it allows must be >= 2 * max(1, "
                             f"samples_per_insert={samples_per_insert}) wide so that inserts and samples cannot "
                             "block each other")
        if min_diff > offset:
            raise ValueError(f"error_buffer={error_buffer} starts above samples_per_insert * min_size_to_sample = "
                             f"{offset:g}: sampling would block forever once the table reaches its minimum size")
        super().__init__(samples_per_insert, min_size_to_sample, min_diff, max_diff)


class Queue(RateLimiter):
    """Every item sampled exactly once, oldest first, at most `size` waiting (Reverb's queue
    preset: use it with a Fifo sampler and remover and max_times_sampled=1, as `Table.queue`)."""

    def __init__(self, size: int) -> None:
        super().__init__(1.0, 1, 0.0, float(size))


class Stack(Queue):
    """Reverb's stack preset: `Queue`'s limits, for a Lifo sampler and remover (as `Table.stack`)."""
