"""Same-process A/B of the stateless env adapter's batched step on a CPU: `StatelessBatchEnv`
of another tree (its adapter.py, loaded from a file) against this tree's, interleaved in blocks
of 300 steps (30 blocks each, the order alternating), one torch thread; medians per step.

    git archive BASE_REV src/relayrl/envs/stateless/adapter.py | tar -x -C /tmp/base
    python bench/stateless_adapter_ab.py /tmp/base/src/relayrl/envs/stateless/adapter.py

One process sees one load, so the ratio holds on a busy host where two processes' figures would not.
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import time

import torch

from relayrl.envs.stateless.adapter import StatelessBatchEnv
from relayrl.envs.stateless.pendulum import make_pendulum


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("base", help="the other tree's src/relayrl/envs/stateless/adapter.py")
    p.add_argument("--batches", type=int, nargs="+", default=[1, 32, 1024])
    args = p.parse_args()
    spec = importlib.util.spec_from_file_location("base_adapter", args.base)
    assert spec is not None and spec.loader is not None
    base = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(base)
    torch.set_num_threads(1)
    for b in args.batches:
        envs = {"base": base.StatelessBatchEnv(make_pendulum(), b, seed=0),
                "this": StatelessBatchEnv(make_pendulum(), b, seed=0)}
        for env in envs.values():
            env.reset(seed=0)
        action = torch.zeros(b, 1)
        times: dict[str, list[float]] = {k: [] for k in envs}
        for block in range(30):
            for name, env in (list(envs.items()) if block % 2 else list(envs.items())[::-1]):
                t0 = time.perf_counter()
                for _ in range(300):
                    env.step(action)
                times[name].append((time.perf_counter() - t0) / 300 * 1e6)
        a, b_ = statistics.median(times["base"]), statistics.median(times["this"])
        print(f"batch {b}: base {a:.1f} us, this {b_:.1f} us per batched step; this / base {b_ / a:.3f}")


if __name__ == "__main__":
    main()
