"""Collection throughput of SAC's actor on Pendulum-v1 against Gymnasium's raw vector envs, same run.

    .venv/bin/python bench/collect.py [--envs 1 8 32 128] [--seconds 2] [--repeats 3] [--steps-per-run 1]
        [--threads 1] [--workers 0] [--json bench/results/collect.json]
    .venv/bin/python bench/collect.py --parts --envs 32    # where a batched step's time goes
    .venv/bin/python bench/collect.py --env relayrl/StatelessPendulum-v0 --envs 256 4096 \
        --vectorization sync --replay-device numpy cpu [--device cuda]

For each N and each vectorization (sync: in this process; async: in worker processes):

  raw    Gymnasium's SyncVectorEnv / AsyncVectorEnv stepped with random actions drawn before
         timing (so the figure is the env alone), same-step autoreset. AsyncVectorEnv runs one
         process per copy; relayrl's async env shares the copies out over `--workers` processes
         (`env.num_workers`; 0, the default, takes one per core), so async rows also time raw
         SyncVectorEnv (`raw sync`): the fastest way Gymnasium offers to step these copies here
  ours   relayrl's Actor: SAC's collect policy (a (256, 256) tanh-Gaussian actor, the sac-batched
         preset's) + our batched env + EnvironmentSteps and EpisodeStats metrics + the
         TransitionWriter inserting into a 1,000,000-item Table. `Actor.collect` takes
         `--steps-per-run` batched steps per call and the writer flushes at the end of each
         call: 1 (the default) is the sac-batched loop, which trains after every batched step;
         larger values are an actor that only collects (a rollout worker), whose writer
         stages steps and inserts them in chunks

With `--env relayrl/StatelessPendulum-v0` the env is the stateless torch Pendulum (all copies
one batch of tensors on `--device`), raw is that env stepped with random actions, and
`--replay-device` compares where the writer keeps frames and actions (numpy: host arrays;
cpu / cuda: torch tensors there; see `replay.device`).

Overhead = ours' time per env step minus raw's, as a % of raw's: the actor loop's cost on top of
the env. The issue's target: under 25% at N = 32. `our env` is relayrl's batched env alone,
stepped with random actions like raw; "loop only" = ours' time minus our env's, as a % of raw's:
the policy, replay and metrics, without what our env layer saves (or costs) against Gymnasium's
vector env. Figures are env steps/s, the median of `--repeats` (3) runs of `--seconds`, raw,
our env and ours alternating so they see the same load (the machine is shared); the spread of
the overhead over the (raw, ours) pairs is printed beside it. torch runs on `--threads` threads
(1 by default; the env is single-threaded too).
"""

from __future__ import annotations

import argparse
import copy
import datetime
import json
import platform
import statistics
import time
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from relayrl.agents.registry import algorithm
from relayrl.envs import make_env
from relayrl.metrics import EnvironmentSteps, EpisodeStats
from relayrl.presets import load_config
from relayrl.training.actor import Actor
from relayrl.training.replay_setup import build_replay
from relayrl.training.replay_setup import replay_device as replay_device_of

ENV = "Pendulum-v1"
STATELESS = "relayrl/StatelessPendulum-v0"


def rate(step_batch: Callable[[], None], n: int, seconds: float) -> float:
    """Env steps/s of calling `step_batch` (n env steps each) for about `seconds`."""
    for _ in range(20):
        step_batch()  # warm-up: first-call costs, caches
    calls, t0 = 0, time.perf_counter()
    while (elapsed := time.perf_counter() - t0) < seconds:
        for _ in range(10):
            step_batch()
        calls += 10
    return calls * n / elapsed


def cycle(step: Callable[[Any], Any], actions: Any) -> Callable[[], None]:
    """A no-argument step that feeds `step` the pre-drawn `actions` in turn."""
    i = 0

    def step_next() -> None:
        nonlocal i
        step(actions[i % len(actions)])
        i += 1

    return step_next


def raw(n: int, vectorization: str, env_id: str = ENV,
        device: str = "cpu") -> tuple[Callable[[], None], Callable[[], None]]:
    if env_id == STATELESS:
        return env_alone(n, "sync", env_id, device)  # relayrl's own env is the raw one
    fns = [lambda: gym.make(ENV, disable_env_checker=True)] * n
    cls = gym.vector.AsyncVectorEnv if vectorization == "async" else gym.vector.SyncVectorEnv
    vec = cls(fns, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
    vec.reset(seed=0)
    actions = np.random.default_rng(0).uniform(-2, 2, (1024, n, 1)).astype(np.float32)
    return cycle(vec.step, actions), vec.close


def env_alone(n: int, vectorization: str, env_id: str = ENV, device: str = "cpu",
              workers: int = 0) -> tuple[Callable[[], None], Callable[[], None]]:
    """relayrl's own batched env (as `ours` builds it) stepped with pre-drawn random actions."""
    env = make_env(env_id, n, vectorization=vectorization, device=device, num_workers=workers)
    env.reset(seed=0)
    acts = torch.rand((1024, n, 1), generator=torch.Generator().manual_seed(0)).mul(4).sub(2).to(device)
    return cycle(env.step, acts), env.close


def ours(n: int, vectorization: str, steps_per_run: int = 1, env_id: str = ENV, device: str = "cpu",
         replay_device: str = "numpy", workers: int = 0) -> tuple[Callable[[], None], Callable[[], None]]:
    c = load_config("sac-batched", [f"env.num_envs={n}", f"env.vectorization={vectorization}",
                                    "train.gradient_steps=0", f"device={device}", f"replay.device={replay_device}"])
    dev = torch.device(device)
    env = make_env(env_id, n, vectorization=vectorization, device=dev, num_workers=workers)
    agent = algorithm("sac").make_agent(c.agent, env.observation_spec, env.action_spec, dev,
                       np.random.default_rng(0), c.train.total_steps)
    table, writer = build_replay(c, env.observation_spec, env.action_spec, run_root=None,  # type: ignore[arg-type]
                                 device=replay_device_of(c, dev, env_id == STATELESS))
    acting = copy.deepcopy(agent.policy_network()).requires_grad_(False)
    actor = Actor(env, agent.collect_policy(lambda: 0, acting), [EnvironmentSteps(), EpisodeStats(), writer], seed=0)
    return (lambda: actor.collect(n * steps_per_run)), env.close


def measure(n: int, vectorization: str, seconds: float, steps_per_run: int, env_id: str = ENV,
            device: str = "cpu", replay_device: str = "numpy", repeats: int = 3, workers: int = 0) -> dict[str, Any]:
    names = ("raw", "ours") if env_id == STATELESS else ("raw", "env", "ours")  # (stateless: raw is our env)
    if vectorization == "async":
        names = ("raw", "raw_sync", "env", "ours")
    figures: dict[str, list[float]] = {name: [] for name in names}
    for _ in range(repeats):
        for name in names:
            step, close = (raw(n, vectorization, env_id, device) if name == "raw"
                           else raw(n, "sync", env_id, device) if name == "raw_sync"
                           else env_alone(n, vectorization, workers=workers) if name == "env"
                           else ours(n, vectorization, steps_per_run, env_id, device, replay_device, workers))
            per_call = n * steps_per_run if name == "ours" else n
            try:
                figures[name].append(rate(step, per_call, seconds))
            finally:
                close()
    r, o = statistics.median(figures["raw"]), statistics.median(figures["ours"])
    e = statistics.median(figures["env"]) if "env" in figures else r
    pairs = sorted(100 * (a / b - 1) for a, b in zip(figures["raw"], figures["ours"], strict=True))
    rs = statistics.median(figures["raw_sync"]) if "raw_sync" in figures else None
    return {"n": n, "vectorization": vectorization, "env": env_id, "replay_device": replay_device,
            "workers": workers if vectorization == "async" else None, "raw_sync_sps": rs,
            "raw_sps": r, "env_sps": e, "ours_sps": o, "overhead_pct": 100 * (r / o - 1),
            # the loop's own cost (policy, replay, metrics) over our env, as a % of raw's time
            "loop_overhead_pct": 100 * (r / o - r / e),
            "pair_overheads_pct": pairs, "figures": figures}


def parts(n: int, vectorization: str, workers: int, steps: int = 3000) -> dict[str, float]:
    """Microseconds per batched step in the policy, in env.step, and in all, timed in the loop."""
    run, close = ours(n, vectorization, workers=workers)
    actor = run.__closure__[0].cell_contents  # type: ignore[index]  # the Actor `ours` built
    spent = {"policy": 0.0, "env": 0.0}

    class Timed:
        """`f` with its calls' time added to spent[key]; other attributes are f's own (the
        actor asks its policy for `env_action`)."""

        def __init__(self, f: Callable[[Any], Any], key: str) -> None:
            self.f, self.key = f, key

        def __call__(self, x: Any) -> Any:
            t = time.perf_counter()
            out = self.f(x)
            spent[self.key] += time.perf_counter() - t
            return out

        def __getattr__(self, name: str) -> Any:
            return getattr(self.f, name)

    actor.policy, actor.env.step = Timed(actor.policy, "policy"), Timed(actor.env.step, "env")
    for _ in range(300):
        run()
    spent.update(policy=0.0, env=0.0)
    t0 = time.perf_counter()
    for _ in range(steps):
        run()
    total = time.perf_counter() - t0
    close()
    return {"policy": 1e6 * spent["policy"] / steps, "env": 1e6 * spent["env"] / steps,
            "rest": 1e6 * (total - spent["policy"] - spent["env"]) / steps, "total": 1e6 * total / steps}


def vs_sync(row: dict[str, Any]) -> str:
    rs = row["raw_sync_sps"]
    return f"  [{rs:,.0f}, {row['ours_sps'] / rs:.2f}x]" if rs else ""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--envs", type=int, nargs="+", default=[1, 8, 32, 128])
    ap.add_argument("--vectorization", nargs="+", default=["sync", "async"], choices=["sync", "async"])
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--repeats", type=int, default=3, help="raw/ours pairs per row; the median is reported")
    ap.add_argument("--steps-per-run", type=int, default=1)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--workers", type=int, default=0, help="async: env.num_workers (0: one per core)")
    ap.add_argument("--env", default=ENV, choices=[ENV, STATELESS])
    ap.add_argument("--device", default="cpu", help="the stateless env's and the policy's device")
    ap.add_argument("--replay-device", nargs="+", default=["numpy"], help="numpy | cpu | cuda (replay.device)")
    ap.add_argument("--parts", action="store_true",
                    help="instead: us per batched step in policy / env.step / the rest, each N and vectorization")
    ap.add_argument("--json")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.parts:
        for vec in args.vectorization:
            for n in args.envs:
                p = parts(n, vec, args.workers)
                print(f"N {n:>4} {vec:>5}: " + ", ".join(f"{k} {v:,.0f} us" for k, v in p.items()), flush=True)
        return
    print(f"torch threads {args.threads}, batched steps per Actor.collect {args.steps_per_run}")
    rows = []
    print(f"env {args.env}, device {args.device}")
    print(f"{'N':>5} {'vectorization':>13} {'replay':>7} {'raw steps/s':>12} {'our env':>9} {'ours steps/s':>13} "
          f"{'overhead':>9} {'loop only':>9}  pairs (min..max)  [async: raw sync steps/s, ours / raw sync]")
    for vec in args.vectorization:
        for n in args.envs:
            if vec == "async" and (n == 1 or args.env == STATELESS):
                continue  # one copy always steps in process; a stateless env is one batch of tensors
            for rd in args.replay_device:
                row = measure(n, vec, args.seconds, args.steps_per_run, args.env, args.device, rd, args.repeats,
                              args.workers)
                rows.append(row)
                lo, hi = row["pair_overheads_pct"][0], row["pair_overheads_pct"][-1]
                print(f"{n:>5} {vec:>13} {rd:>7} {row['raw_sps']:>12,.0f} {row['env_sps']:>9,.0f} "
                      f"{row['ours_sps']:>13,.0f} {row['overhead_pct']:>8.1f}% {row['loop_overhead_pct']:>8.1f}%  "
                      f"{lo:.1f}..{hi:.1f}%" + vs_sync(row), flush=True)
    if args.json:
        meta = {"date": datetime.date.today().isoformat(), "machine": platform.platform(),
                "threads": args.threads, "steps_per_run": args.steps_per_run, "workers": args.workers,
                "cpus": __import__("os").cpu_count(), "torch": torch.__version__, "gymnasium": gym.__version__}
        with open(args.json, "w") as f:
            json.dump({"meta": meta, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
