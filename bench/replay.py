"""Replay: relayrl's Table + TransitionWriter against SB3's and TorchRL's buffers, same run, as ratios.

    .venv/bin/python bench/replay.py [--peer-python bench/.venv-peers/bin/python] [--seconds 1.5]
        [--json bench/results/replay.json]

Items are Pendulum-sized transitions (obs 3 float32, action 1 float32, reward float32, done
flags); episodes are truncated every 200 steps, as Pendulum's are. Every (library, measurement)
runs in its own fresh process and the three libraries run one after another, so they see the
same load on this shared machine; a figure is the median of 3 timed repeats of `--seconds`.
Inputs are built before timing and cycled through, so the timed loop is the buffer alone.
Every worker runs with torch.set_num_threads(1): no replay op here is big enough to split.

  insert-1   single-transition inserts/s (relayrl num_envs=1, SB3 n_envs=1, TorchRL add)
  insert-32  transitions/s in batches of 32 (num_envs=32, SB3 n_envs=32, TorchRL extend of 32)
  sample     uniform sample of 256 from a full 1,000,000-item buffer, batches/s (fill untimed)
  per        prioritized sample 256 + update_priorities 256 from 1,000,000, iterations/s, with
             the compiled sum tree when numba is installed (relayrl[fast]); `per-numpy` (relayrl
             only) is the same with RELAYRL_NUMBA=0, the NumPy tree every install has
  pixel      relayrl only: frame_stack=4, uint8 [4,84,84] obs, max_size 100,000, filled with
             100,000 transitions in episodes of ~500 steps ending terminated; VmRSS growth
             (before vs after creating + filling, fresh process) and sample-of-32 batches/s

Memory floor. A `floor` process measures this machine's copy bandwidth (np.copyto of 256 MB;
bytes copied per second) and random-gather time (np.take of 256 random rows of a [1M, 16]
uint8 array, NumPy's cheapest gather; its per-call overhead included). An op's floor time is
    bytes / copy_bandwidth + (random_rows / 256) * gather_256_time
bytes: the logical bytes the op must move, 33 per transition (obs 12, next_obs 12, action 4,
reward 4, done 1), for a pixel sample 2 * 4*84*84 per item; random_rows: items read plus
priorities written at random places (inserts are sequential: 0). Sum-tree walks, locks and
Python dispatch are not in the floor: it is what a buffer reaching memory speed would do, and
"% floor" = figure / (1 / floor time).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from typing import Any

from _workers import report, run_worker  # bench/ is on sys.path when a script runs

N, BATCH, EP_LEN, ITEM_BYTES = 1_000_000, 256, 200, 33
PIXEL_N, PIXEL_STACK_BYTES = 100_000, 4 * 84 * 84
TASKS = ["insert-1", "insert-32", "sample", "per"]
LIBS = ["relayrl", "sb3", "torchrl"]


def rss_bytes() -> int:
    with open("/proc/self/status") as f:  # no psutil in either venv; VmRSS is what psutil reads
        return next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmRSS:"))


def timed(step: Callable[[], int], seconds: float, finish: Callable[[], Any] | None = None) -> dict:
    """step() does some ops and returns how many units it did; median units/s of 3 repeats."""
    step()  # warm-up: first-call allocations and lazy initialisation are not steady state
    rates = []
    for _ in range(3):
        units, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            units += step()
        if finish is not None:
            finish()  # e.g. a writer's buffered rows must be in the table before the clock stops
        rates.append(units / (time.perf_counter() - t0))
    return {"rate": statistics.median(rates), "repeats": rates}


def cycling(call: Callable[[Any], Any], pool: list, units: int) -> Callable[[], int]:
    """A timed step: 50 calls on consecutive pool entries (one env step each), `units` per call."""
    i = 0

    def step() -> int:
        nonlocal i
        for _ in range(50):
            call(pool[i])
            i = (i + 1) % len(pool)
        return 50 * units

    return step


# ---- relayrl -------------------------------------------------------------------------------
def relayrl_task(task: str, seconds: float) -> dict:
    import numpy as np
    import torch

    from relayrl.replay import Fifo, MinSize, Prioritized, Table, TransitionWriter, Uniform
    from relayrl.specs import ArraySpec
    from relayrl.types import Transition

    torch.set_num_threads(1)
    if task == "pixel":
        return relayrl_pixel(seconds)
    if task == "per-numpy":
        os.environ["RELAYRL_NUMBA"] = "0"  # read when the table's sampler builds its tree
        task = "per"
    f32 = ArraySpec((3,), torch.float32), ArraySpec((1,), torch.float32)

    def steps(b: int, count: int, ep_len: int = EP_LEN) -> list[Transition]:
        g = torch.Generator().manual_seed(0)
        no = torch.zeros(b, dtype=torch.bool)
        return [Transition(torch.rand(b, 3, generator=g), torch.rand(b, 1, generator=g), torch.rand(b, generator=g),
                           torch.rand(b, 3, generator=g), no, no | ((i + 1) % ep_len == 0)) for i in range(count)]

    table = Table("r", N, Prioritized(0.6) if task == "per" else Uniform(), Fifo(), MinSize(1), seed=0)
    if task.startswith("insert"):
        b = 1 if task == "insert-1" else 32
        writer = TransitionWriter(table, b, *f32, gamma=0.99, n_step=1, frame_stack=1)
        return timed(cycling(writer, steps(b, EP_LEN), b), seconds, getattr(writer, "flush", None))
    # Fill fast: 1,000 envs per writer call, no episode ends, until the table is full.
    writer = TransitionWriter(table, 1000, *f32, gamma=0.99, n_step=1, frame_stack=1)
    pool = steps(1000, 4, ep_len=10**9)
    while table.size < N:
        writer(pool[table.size % 4])
    if hasattr(writer, "flush"):
        writer.flush()
    if task == "sample":
        return timed(lambda: (table.sample(BATCH), 1)[1], seconds)
    prios = list(np.random.default_rng(0).uniform(0.01, 2.0, (64, BATCH)))
    out = timed(cycling(lambda p: table.update_priorities(table.sample(BATCH)[1].key, p), prios, 1), seconds)
    return {**out, "tree": type(table.sampler.tree).__name__}


def relayrl_pixel(seconds: float) -> dict:
    import numpy as np
    import torch

    from relayrl.replay import Fifo, MinSize, Table, TransitionWriter, Uniform
    from relayrl.specs import ArraySpec
    from relayrl.types import Transition

    rng = np.random.default_rng(0)
    frames = torch.from_numpy(rng.integers(0, 256, (1024, 84, 84), dtype=np.uint8))  # 7 MB pool, reused
    act, rew = torch.zeros(1, 1), torch.zeros(1)
    no, yes = torch.zeros(1, dtype=torch.bool), torch.ones(1, dtype=torch.bool)
    before = rss_bytes()
    table = Table("pixels", PIXEL_N, Uniform(), Fifo(), MinSize(1), seed=0)
    writer = TransitionWriter(table, 1, ArraySpec((4, 84, 84), torch.uint8), ArraySpec((1,), torch.float32),
                              gamma=0.99, n_step=1, frame_stack=4)
    t, ep_left = 0, int(rng.integers(450, 551))
    while table.size < PIXEL_N:  # an item enters when its next row is written: one step after the step
        j = t % 1019  # a sliding window of the pool stands in for a FrameStack observation
        end = ep_left == 1
        writer(Transition(frames[j:j + 4][None], act, rew, frames[j + 1:j + 5][None], yes if end else no, no))
        t, ep_left = t + 1, (int(rng.integers(450, 551)) if end else ep_left - 1)
    if hasattr(writer, "flush"):
        writer.flush()
    after = rss_bytes()
    out = timed(lambda: (table.sample(32), 1)[1], seconds)
    out.update(rss_before=before, rss_after=after, rss_growth=after - before, table_size=table.size,
               transitions=t)
    return out


# ---- Stable-Baselines3 ---------------------------------------------------------------------
def sb3_task(task: str, seconds: float) -> dict:
    import numpy as np
    import torch
    from gymnasium import spaces
    from stable_baselines3.common.buffers import ReplayBuffer

    torch.set_num_threads(1)
    if task == "per":
        return {"error": "n/a (SB3 has no prioritized buffer)"}
    box3, box1 = spaces.Box(-1, 1, (3,), np.float32), spaces.Box(-1, 1, (1,), np.float32)
    b = 32 if task == "insert-32" else 1
    rb = ReplayBuffer(N, box3, box1, device="cpu", n_envs=b)
    if task == "sample":
        # Fill by writing its arrays: this is the state 1M add() calls leave, minus the wait.
        rng = np.random.default_rng(0)
        for arr in (rb.observations, rb.next_observations, rb.actions, rb.rewards):
            arr[:] = rng.random(arr.shape, dtype=np.float32)
        rb.full, rb.pos = True, 0
        return timed(lambda: (rb.sample(BATCH), 1)[1], seconds)
    rng = np.random.default_rng(0)
    pool = []
    for i in range(EP_LEN):
        trunc = (i + 1) % EP_LEN == 0
        pool.append((rng.random((b, 3), dtype=np.float32), rng.random((b, 3), dtype=np.float32),
                     rng.random((b, 1), dtype=np.float32), rng.random(b, dtype=np.float32),
                     np.full(b, trunc), [{"TimeLimit.truncated": trunc} for _ in range(b)]))
    return timed(cycling(lambda args: rb.add(*args), pool, b), seconds)


# ---- TorchRL -------------------------------------------------------------------------------
def torchrl_task(task: str, seconds: float) -> dict:
    import torch
    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage, TensorDictPrioritizedReplayBuffer, TensorDictReplayBuffer

    torch.set_num_threads(1)

    def tds(n: int, ep_len: int = EP_LEN) -> TensorDict:
        g = torch.Generator().manual_seed(0)
        trunc = (torch.arange(n) % ep_len == ep_len - 1)[:, None]
        return TensorDict({"observation": torch.rand(n, 3, generator=g), "action": torch.rand(n, 1, generator=g),
                           "next": {"observation": torch.rand(n, 3, generator=g),
                                    "reward": torch.rand(n, 1, generator=g),
                                    "done": trunc, "terminated": torch.zeros(n, 1, dtype=torch.bool),
                                    "truncated": trunc}}, batch_size=[n])

    if task == "per":
        try:
            rb: Any = TensorDictPrioritizedReplayBuffer(alpha=0.6, beta=0.4, storage=LazyTensorStorage(N),
                                                        batch_size=BATCH)
        except Exception as e:  # torch 2.13 wheels lack torchrl's C++ segment trees
            return {"error": f"n/a (error {type(e).__name__}: {str(e).splitlines()[0][:80]})"}
    else:
        rb = TensorDictReplayBuffer(storage=LazyTensorStorage(N), batch_size=BATCH)
    if task.startswith("insert"):
        b = 1 if task == "insert-1" else 32
        big = tds(EP_LEN * b)  # Pendulum-like vector env: all b envs truncate on the same step
        pool = [big[i] for i in range(EP_LEN)] if b == 1 else [big[i * b:(i + 1) * b] for i in range(EP_LEN)]
        return timed(cycling(rb.add if b == 1 else rb.extend, pool, b), seconds)
    rb.extend(tds(N))
    if task == "sample":
        return timed(lambda: (rb.sample(), 1)[1], seconds)
    prios = list(torch.rand(64, BATCH) * 2 + 0.01)
    return timed(cycling(lambda p: rb.update_priority(rb.sample()["index"], p), prios, 1), seconds)


# ---- memory floor ------------------------------------------------------------------------
def floor_task() -> dict:
    import numpy as np

    src = np.random.default_rng(0).random(256 * 2**20 // 8)  # 256 MB, far above any cache
    dst = np.empty_like(src)
    copy_s = []
    for _ in range(5):
        t0 = time.perf_counter()
        np.copyto(dst, src)
        copy_s.append(time.perf_counter() - t0)
    rows = np.zeros((N, 16), dtype=np.uint8)
    rows[:] = 1  # touch every page so the gather does not hit fresh zero pages
    idx = np.random.default_rng(1).integers(0, N, (2000, 256))
    t0 = time.perf_counter()
    for k in range(2000):
        rows.take(idx[k], axis=0)
    gather_s = (time.perf_counter() - t0) / 2000
    return {"copy_gb_s": src.nbytes / statistics.median(copy_s) / 1e9, "gather_256_us": gather_s * 1e6}


def floor_rate(floor: dict, bytes_per_op: float, random_rows: float) -> float:
    return 1.0 / (bytes_per_op / (floor["copy_gb_s"] * 1e9) + random_rows / 256 * floor["gather_256_us"] * 1e-6)


# ---- driver ------------------------------------------------------------------------------
def worker(which: str, task: str, seconds: float) -> None:
    if which == "floor":
        out = floor_task()
    else:
        out = {"relayrl": relayrl_task, "sb3": sb3_task, "torchrl": torchrl_task}[which](task, seconds)
    report(out)


def spawn(python: str, which: str, task: str, seconds: float) -> dict:
    result, proc = run_worker(python, __file__, [which, task, str(seconds)])
    if result is not None:
        return result
    return {"error": f"worker failed (rc {proc.returncode}): {proc.stderr.strip().splitlines()[-1:]}"}


def cell(r: dict, floor: float) -> str:
    return f"{r['rate']:,.0f} ({100 * r['rate'] / floor:.2g}% floor)" if "rate" in r else r["error"]


def report_table(res: dict[str, dict[str, dict]], pix: dict, floor: dict) -> tuple[list[str], dict, dict]:
    """Markdown lines, floors (ops/s) and targets (text, met) for the table."""
    # (bytes per op, random rows per op, unit) for the floor; see the module docstring.
    shape = {"insert-1": (ITEM_BYTES, 0, "inserts/s"), "insert-32": (ITEM_BYTES, 0, "transitions/s"),
             "sample": (BATCH * ITEM_BYTES, BATCH, "batches/s"),
             "per": (BATCH * (ITEM_BYTES + 8), 2 * BATCH, "iters/s")}
    floors = {t: floor_rate(floor, b, r) for t, (b, r, _) in shape.items()}
    floors["pixel"] = floor_rate(floor, 32 * (2 * PIXEL_STACK_BYTES + 9), 32 * 8)

    def ratio(task: str, peer: str) -> float | None:
        a, b = res[task]["relayrl"], res[task][peer]
        return a["rate"] / b["rate"] if "rate" in a and "rate" in b else None

    rl = {t: res[t]["relayrl"].get("rate", 0.0) for t in TASKS}
    gb = pix.get("rss_growth", float("inf")) / 1e9
    target = {"insert-1": (">= 100,000/s", rl["insert-1"] >= 1e5),
              "insert-32": (">= 1,000,000/s", rl["insert-32"] >= 1e6),
              "sample": (">= 2x SB3, >= 3x TorchRL", (ratio("sample", "sb3") or 0) >= 2
                         and (ratio("sample", "torchrl") or 0) >= 3),
              "per": (">= 5,000/s", rl["per"] >= 5e3), "pixel-rss": ("<= 1.1 GB", gb <= 1.1)}
    fmt = lambda x: "n/a" if x is None else f"{x:.2f}"  # noqa: E731
    yes = {t: "yes" if v[1] else "NO" for t, v in target.items()}
    lines = [f"floor: copy {floor.get('copy_gb_s', 0):.2f} GB/s, gather of 256 random 16-byte rows "
             f"{floor.get('gather_256_us', 0):.1f} us", "",
             "| measurement | relayrl | SB3 | TorchRL | relayrl/SB3 | relayrl/TorchRL | target | met | floor |",
             "|---|---|---|---|---|---|---|---|---|"]
    for t in TASKS:
        r = res[t]
        lines.append(f"| {t} ({shape[t][2]}) | {cell(r['relayrl'], floors[t])} | {cell(r['sb3'], floors[t])} | "
                     f"{cell(r['torchrl'], floors[t])} | {fmt(ratio(t, 'sb3'))} | {fmt(ratio(t, 'torchrl'))} | "
                     f"{target[t][0]} | {yes[t]} | {floors[t]:,.0f} |")
    f32_gb = PIXEL_N * 2 * PIXEL_STACK_BYTES * 4 / 1e9  # float32 obs + next_obs stacks per item
    lines.append(f"| pixel sample-32 (batches/s) | {cell(pix, floors['pixel'])} | - | - | - | - | - | - | "
                 f"{floors['pixel']:,.0f} |")
    lines.append(f"| pixel RSS growth, 100k items (GB) | {gb:.3f} ({f32_gb / gb:.0f}x under {f32_gb:.1f} GB of "
                 f"float32 stacks) | - | - | - | - | <= 1.1 GB | {yes['pixel-rss']} | - |")
    return lines, floors, {t: {"target": v[0], "met": v[1]} for t, v in target.items()}


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        worker(sys.argv[2], sys.argv[3], float(sys.argv[4]))
        return
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--peer-python", default="bench/.venv-peers/bin/python")
    p.add_argument("--seconds", type=float, default=1.5, help="length of one timed repeat")
    p.add_argument("--json", help="also write every result here")
    args = p.parse_args()
    started = datetime.datetime.now().isoformat(timespec="seconds")
    floor = spawn(sys.executable, "floor", "-", 0)
    res: dict[str, dict[str, dict]] = {}
    for task in TASKS:  # the three libraries back to back, so they share the machine's load
        res[task] = {lib: spawn(sys.executable if lib == "relayrl" else args.peer_python, lib, task, args.seconds)
                     for lib in LIBS}
        print(f"{task}: " + ", ".join(f"{k} {v.get('rate', v.get('error'))}" for k, v in res[task].items()),
              file=sys.stderr, flush=True)
    per_numpy = spawn(sys.executable, "relayrl", "per-numpy", args.seconds)
    pix = spawn(sys.executable, "relayrl", "pixel", args.seconds)
    lines, floors, targets = report_table(res, pix, floor)
    lines.insert(lines.index("|---|---|---|---|---|---|---|---|---|") + 1 + TASKS.index("per") + 1,
                 f"| per, NumPy tree (RELAYRL_NUMBA=0; relayrl's per row: {res['per']['relayrl'].get('tree')}) | "
                 f"{cell(per_numpy, floors['per'])} | - | - | - | - | - | - | {floors['per']:,.0f} |")
    print("\n".join(lines))
    if args.json:
        meta = {"started": started, "command": " ".join([os.path.relpath(sys.executable), *sys.argv]),
                "machine": f"{platform.machine()} {os.cpu_count()} cores", "python": platform.python_version(),
                "seconds_per_repeat": args.seconds}
        with open(args.json, "w") as f:
            json.dump({"meta": meta, "floor": floor, "floor_rates": floors, "results": res, "pixel": pix,
                       "per_numpy": per_numpy,
                       "targets": targets, "table": lines}, f, indent=1)


if __name__ == "__main__":
    main()
