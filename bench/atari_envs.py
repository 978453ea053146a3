"""Atari Pong stepping through relayrl's batched envs: env.vectorization sync, async and ale, same run.

    python bench/atari_envs.py [--envs 1 8] [--seconds 3] [--repeats 3] [--threads 0]

Each row is N copies of relayrl/Atari-Pong-v0 stepped with random actions (drawn before timing)
through `make_env`: the env alone, as the Actor sees it (frames stacked, episode ends handled).
sync steps the Gymnasium copies one by one in this process, async shares them out over worker
processes (one per core beside this one), ale steps them in ale-py's C++ vector env on
`--threads` threads (0: one per core). Figures are env steps/s, the median of `--repeats` runs of
`--seconds`, the vectorizations alternating so that they see the same load.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import torch

from relayrl.envs import make_env

PONG = "relayrl/Atari-Pong-v0"


def steps_per_s(n: int, vectorization: str, seconds: float, threads: int) -> float:
    env = make_env(PONG, n, vectorization=vectorization, num_workers=threads if vectorization == "ale" else 0)
    env.reset(seed=0)
    actions = [torch.randint(0, 6, (n,)) for _ in range(64)]
    for a in actions[:8]:  # warm-up
        env.step(a)
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        env.step(actions[steps % 64])
        steps += 1
    rate = steps * n / (time.perf_counter() - t0)
    env.close()
    return rate


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--envs", type=int, nargs="+", default=[1, 8])
    p.add_argument("--vectorization", nargs="+", default=["sync", "async", "ale"], choices=["sync", "async", "ale"])
    p.add_argument("--seconds", type=float, default=3.0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=0, help="ale: ale-py's threads (0: one per core)")
    args = p.parse_args()
    if min(args.envs) < 1 or args.seconds <= 0 or args.repeats < 1 or args.threads < 0:
        print("bench/atari_envs.py: --envs >= 1, --seconds > 0, --repeats >= 1 and --threads >= 0", file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    print(f"{'N':>4} " + " ".join(f"{v:>14}" for v in args.vectorization) + "   ale / sync")
    for n in args.envs:
        runs: dict[str, list[float]] = {v: [] for v in args.vectorization}
        for _ in range(args.repeats):
            for v in args.vectorization:
                runs[v].append(steps_per_s(n, v, args.seconds, args.threads))
        med = {v: statistics.median(r) for v, r in runs.items()}
        ratio = f"{med['ale'] / med['sync']:.2f}x" if "ale" in med and "sync" in med else "-"
        print(f"{n:>4} " + " ".join(f"{med[v]:>14,.0f}" for v in args.vectorization) + f"   {ratio:>10}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
