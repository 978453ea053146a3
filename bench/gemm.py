"""How close the actor's matmul runs to this core's peak (issue 5).

    .venv/bin/python bench/gemm.py [--threads 1] [--rows 32] [--width 256]

SAC's collect policy at N = 32 spends three quarters of its time in one [rows, width] x
[width, width] float32 matmul. This prints, per way of computing it, us per call (best of 5
timings of a tight loop) and GFLOP/s, beside a 1024^3 matmul whose rate is the core's
practical peak: torch (MKL) and NumPy (OpenBLAS). `--threads` sets torch's intra-op threads;
NumPy's OpenBLAS takes its thread count from OPENBLAS_NUM_THREADS when the process starts
(run with OPENBLAS_NUM_THREADS=1 to compare one core with one core).
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable

import numpy as np
import torch


def best_us(fn: Callable[[], object], calls: int) -> float:
    for _ in range(max(1, calls // 10)):
        fn()
    best = float("inf")
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(calls):
            fn()
        best = min(best, (time.perf_counter() - t0) / calls)
    return best * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--rows", type=int, default=32)
    ap.add_argument("--width", type=int, default=256)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    g = torch.Generator().manual_seed(0)
    r, w = args.rows, args.width
    x, weight, bias = torch.randn(r, w, generator=g), torch.randn(w, w, generator=g), torch.randn(w, generator=g)
    w_t = weight.t()  # [in, out] view of nn.Linear's [out, in], as MLPInference uses it
    x_np, w_np = x.numpy(), w_t.contiguous().numpy()
    big_t = torch.randn(1024, 1024, generator=g)
    big_np = big_t.numpy()
    small_flop, big_flop = 2 * r * w * w, 2 * 1024**3
    rows = [
        (f"torch.addmm(b, x, W.t())  [{r}, {w}] x [{w}, {w}]", lambda: torch.addmm(bias, x, w_t), small_flop, 3000),
        (f"torch.mm(x, W.t())        [{r}, {w}] x [{w}, {w}]", lambda: torch.mm(x, w_t), small_flop, 3000),
        (f"numpy x @ W               [{r}, {w}] x [{w}, {w}]", lambda: x_np @ w_np, small_flop, 3000),
        ("torch.mm                  1024^3", lambda: torch.mm(big_t, big_t), big_flop, 20),
        ("numpy @                   1024^3", lambda: big_np @ big_np, big_flop, 20),
    ]
    print(f"torch threads {args.threads}, OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}, "
          f"torch {torch.__version__}, numpy {np.__version__}")
    print(f"{'matmul':<50} {'us/call':>10} {'GFLOP/s':>8}")
    for name, fn, flop, calls in rows:
        us = best_us(fn, calls)
        print(f"{name:<50} {us:>10.1f} {flop / us / 1e3:>8.1f}")


if __name__ == "__main__":
    main()
