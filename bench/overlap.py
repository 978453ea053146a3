"""Can the actor's forward pass overlap with Python work on a second core? (issue 5)

    .venv/bin/python bench/overlap.py [--rows 32] [--busy-us 300] [--repeats 300]

A TorchScript (256, 256) MLP forward of `--rows` rows (SAC's actor on Pendulum) next to
`--busy-us` of pure-Python busy work (standing in for stepping the envs), four ways: back to
back; `torch.jit.fork` from a scripted launcher that returns the Future (the inter-op pool);
a Python worker thread fed through a queue; the same with a `time.sleep(0)` hand-off. Prints
us per round. Overlap would show as rounds shorter than back to back. torch runs on one
intra-op thread; leave the second core idle.
"""

from __future__ import annotations

import argparse
import queue
import threading
import time
from collections.abc import Callable

import torch


@torch.jit.script
def forward(x: torch.Tensor, w1: torch.Tensor, b1: torch.Tensor, w2: torch.Tensor, b2: torch.Tensor,
            w3: torch.Tensor, b3: torch.Tensor) -> torch.Tensor:
    h = torch.relu(torch.addmm(b1, x, w1))
    h = torch.relu(torch.addmm(b2, h, w2))
    return torch.addmm(b3, h, w3)


@torch.jit.script
def launch(x: torch.Tensor, w1: torch.Tensor, b1: torch.Tensor, w2: torch.Tensor, b2: torch.Tensor,
           w3: torch.Tensor, b3: torch.Tensor) -> torch.jit.Future[torch.Tensor]:
    return torch.jit.fork(forward, x, w1, b1, w2, b2, w3, b3)


def busy(us: float) -> None:
    t = time.perf_counter()
    while (time.perf_counter() - t) * 1e6 < us:
        pass


def per_round(fn: Callable[[], None], repeats: int) -> float:
    for _ in range(20):
        fn()
    t = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - t) / repeats * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=32)
    ap.add_argument("--busy-us", type=float, default=300.0)
    ap.add_argument("--repeats", type=int, default=300)
    a = ap.parse_args()
    torch.set_num_threads(1)
    x = torch.randn(a.rows, 3)
    w = (torch.randn(3, 256), torch.randn(256), torch.randn(256, 256), torch.randn(256), torch.randn(256, 2),
         torch.randn(2))
    inq: queue.SimpleQueue = queue.SimpleQueue()
    outq: queue.SimpleQueue = queue.SimpleQueue()

    def worker() -> None:
        while (item := inq.get()) is not None:
            outq.put(forward(item, *w))

    threading.Thread(target=worker, daemon=True).start()

    def thread_round(hand_off: bool) -> None:
        inq.put(x)
        if hand_off:
            time.sleep(0)  # let the worker take the GIL and enter the scripted call
        busy(a.busy_us)
        outq.get()

    def fork_round() -> None:
        fut = launch(x, *w)
        busy(a.busy_us)
        fut.wait()

    def back_to_back() -> None:
        forward(x, *w)
        busy(a.busy_us)

    rows = [("forward alone", lambda: forward(x, *w)), ("busy alone", lambda: busy(a.busy_us)),
            ("back to back", back_to_back), ("torch.jit.fork + wait", fork_round),
            ("worker thread", lambda: thread_round(False)),
            ("worker thread, sleep(0) hand-off", lambda: thread_round(True))]
    print(f"{'way':<34} {'us per round':>12}")
    for name, fn in rows:
        print(f"{name:<34} {per_round(fn, a.repeats):>12.1f}", flush=True)
    inq.put(None)


if __name__ == "__main__":
    main()
