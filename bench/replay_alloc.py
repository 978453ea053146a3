"""A host replay's frames allocated by `replay.storage.lazy_zeros` against `np.zeros`, in one
process, alternating: 100,000 Pong frames (84x84 uint8) written once, then 20,000 random batches
of 32 gathered, 4 rounds each (the median printed).

    python bench/replay_alloc.py
"""

from __future__ import annotations

import time

import numpy as np

from relayrl.replay.storage import lazy_zeros

ROWS, SHAPE, BATCHES = 100_000, (84, 84), 20_000


def run(make, frame: np.ndarray, batches: np.ndarray) -> tuple[float, float]:
    t0 = time.perf_counter()
    frames = make((ROWS, *SHAPE), np.dtype(np.uint8))
    for i in range(ROWS):
        frames[i] = frame
    t1 = time.perf_counter()
    for rows in batches:
        frames[rows].sum()
    return t1 - t0, time.perf_counter() - t1


def main() -> None:
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 255, SHAPE, dtype=np.uint8)
    batches = rng.integers(0, ROWS, (BATCHES, 32))
    makers = {"np.zeros": lambda shape, dtype: np.zeros(shape, dtype), "lazy_zeros": lazy_zeros}
    times: dict[str, list[tuple[float, float]]] = {name: [] for name in makers}
    for r in range(4):
        for name in (list(makers) if r % 2 == 0 else list(makers)[::-1]):
            times[name].append(run(makers[name], frame, batches))
    for name, got in times.items():
        write, gather = (float(np.median([t[k] for t in got])) for k in (0, 1))
        print(f"{name:10s} write {ROWS:,} frames {write:.3f} s, {BATCHES:,} batches of 32 gathered {gather:.3f} s")


if __name__ == "__main__":
    main()
