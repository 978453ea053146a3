"""Distributed relayrl on Ray: collection scaling, learner slowdown, replay-server RPC cost, and a model.

    .venv/bin/python bench/distributed.py --part all        # every part: ~4 min on 2 cores, Ray start-ups included
    .venv/bin/python bench/distributed.py --part collect  [--seconds 8] [--step-ms 3.7] [--envs busy minitaur]
    .venv/bin/python bench/distributed.py --part learner  [--grad-steps 600] [--env busy] [--worker-niceness 0]
    .venv/bin/python bench/distributed.py --part server   [--seconds 1] [--batches 1 32 256]
    .venv/bin/python bench/distributed.py --part simulate [--spi 32] [--learner-sps 1000] [--shards 4]
                                                          [--numpy-batches] [--gbps 10] ...
    --quick: a smoke run (a few seconds of timing per figure; Ray's start-ups still take their time)

Every part builds relayrl's own pieces (ReplayServer, VariableContainer, RolloutWorker, RemoteTable,
Learner) and wires them with Ray as distributed/driver.py does; nothing here trains a policy.

  collect   env steps/s the replay server accepts from K = 1 and K = 2 RolloutWorker actors, each
            with two `collect(1024, 0, True)` calls kept queued (random policy; gradient_steps = 0,
            so the MinSize rate limiter never blocks an insert), timed for --seconds after a
            warm-up. Envs: relayrl/MinitaurBullet-v0 (pybullet) and BusyEnv (a fixed CPU cost per
            step). Target: K=2 >= 1.7 x K=1.
  learner   SAC (256, 256), batch 256, one torch thread: gradient steps/s of a Learner on a filled
            in-process Table alone, then of the same Learner sampling through RemoteTable from a
            ReplayServer actor while K = 1 (then K = 2) actors collect the slow env and the learner
            pushes weights every 50 steps. The rate limiter never throttles the learner (MinSize).
            Target: K=1 >= 0.70 x alone. K=2 leaves the learner no core of its own on 2 CPUs; Ray
            runs its workers at nice 15 and the driver at 0, which decides who yields
            (--worker-niceness 0 to see the difference).
  server    items/s through ReplayServer.ingest (StepChunks of b env steps) and .sample(b, 1, t),
            b in --batches: in-process (a plain object), a Ray actor called from the driver (one
            call in flight, as a rollout actor's ChunkShipper) and from two client actors at once;
            the server process's CPU time per call; `sample_np`, the same sample answering NumPy
            arrays instead of torch tensors. Fits the `simulate` constants.
  simulate  no Ray: bytes per chunk / batch / weight push for SAC (256, 256) with BipedalWalker's
            shapes (obs 24, act 4), then a steady-state bottleneck model of K = 1..64 actors with 1
            and S replay shards (docs/distributed.md). A model, not a measurement: its server
            costs default to a `--part server` run on the shared 2-core machine, its learner rate
            to an assumed GPU learner.

The machine is shared: compare figures taken in the same run.
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import pickle
import platform
import sys
import tempfile
import time
import uuid
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # so that `bench.distributed:BusyEnv` imports here and in Ray workers
    sys.path.insert(0, str(ROOT))

from relayrl.agents.registry import algorithm  # noqa: E402
from relayrl.config import Config, from_dict, to_dict  # noqa: E402
from relayrl.envs import make_env  # noqa: E402
from relayrl.replay.writers import StepChunk  # noqa: E402
from relayrl.training.learner import Learner  # noqa: E402
from relayrl.training.replay_setup import build_replay  # noqa: E402

BUSY = "bench.distributed:BusyEnv"
MINITAUR = "relayrl/MinitaurBullet-v0"
ENVS = {"busy": BUSY, "minitaur": MINITAUR}
STEP_MS_VAR = "RELAYRL_BENCH_STEP_MS"  # BusyEnv's cost; Ray workers inherit the driver's environment
OBS, ACT, EPISODE = 24, 4, 1000  # BipedalWalker's obs and action sizes; Minitaur's episode length
BATCH = 256


# ---- the slow env ---------------------------------------------------------------------------
class BusyEnv(gym.Env):
    """24 floats in, 4 actions out, 1000-step episodes (truncated), and a fixed CPU cost per step:
    a busy-wait of $RELAYRL_BENCH_STEP_MS ms (default 3.7, about Minitaur's), so that it loads
    a core the way a CPU-bound simulator does; a sleeping env would scale with any K."""

    metadata = {"render_modes": []}

    def __init__(self, render_mode: str | None = None) -> None:
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (OBS,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (ACT,), np.float32)
        self.step_s = float(os.environ.get(STEP_MS_VAR, "3.7")) / 1000
        self._rng = np.random.default_rng(0)
        self._t = 0

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        self._t = 0
        return self._rng.standard_normal(OBS, dtype=np.float32), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        end = time.perf_counter() + self.step_s
        while time.perf_counter() < end:
            pass
        self._t += 1
        obs = self._rng.standard_normal(OBS, dtype=np.float32)
        return obs, float(-np.square(action).sum()), False, self._t >= EPISODE, {}


# ---- shared pieces --------------------------------------------------------------------------
def bench_config(env_id: str, num_actors: int, min_size: int = 1000, size: int = 100_000) -> Config:
    """SAC (256, 256), batch 256, one torch thread; gradient_steps = 0 makes the rate limiter
    MinSize: inserts never block and, past min_size, samples never do either."""
    return from_dict({
        "algo": "sac", "seed": 0, "device": "cpu",
        "env": {"id": env_id, "num_envs": 1},
        "train": {"total_steps": 10**9, "initial_collect_steps": min_size, "gradient_steps": 0, "torch_threads": 1},
        "replay": {"size": size, "min_size_to_sample": min_size},
        "distributed": {"num_actors": max(num_actors, 1)},
        "agent": {"actor_hidden": [256, 256], "critic_hidden": [256, 256], "batch_size": BATCH},
    })


def specs(env_id: str) -> tuple[Any, Any]:
    env = make_env(env_id)
    try:
        return env.observation_spec, env.action_spec
    finally:
        env.close()


def fake_chunks(steps: int, obs: int = OBS, act: int = ACT, seed: int = 0) -> list[StepChunk]:
    """StepChunks of `steps` steps of one env with 1000-step episodes, enough of them that the
    cycle repeats (the episode ends fall where a real actor's would)."""
    rng = np.random.default_rng(seed)
    out = []
    for j in range(math.lcm(steps, EPISODE) // steps):
        t = j * steps + np.arange(steps)
        done = ((t + 1) % EPISODE == 0)[:, None]
        out.append(StepChunk(rng.standard_normal((steps, 1, obs), dtype=np.float32),
                             rng.uniform(-1, 1, (steps, 1, act)).astype(np.float32),
                             rng.standard_normal((steps, 1), dtype=np.float32), done, np.zeros_like(done),
                             rng.standard_normal((int(done.sum()), obs), dtype=np.float32)))
    return out


def sac_agent(c: Config, obs_spec: Any, act_spec: Any) -> Any:
    torch.manual_seed(0)
    return algorithm("sac").make_agent(c.agent, obs_spec, act_spec, torch.device("cpu"), np.random.default_rng(1),
                      c.train.total_steps)


def machine() -> str:
    import ray

    return (f"date {datetime.datetime.now().isoformat(timespec='minutes')} | {platform.platform()} | "
            f"cpus {os.cpu_count()} | python {platform.python_version()} | torch {torch.__version__} | "
            f"ray {ray.__version__} | gymnasium {gym.__version__}")


# ---- Ray wiring (as distributed/driver.py does it) -----------------------------------------------
class Cluster:
    """A replay server and a variable container under the names RolloutWorker looks up, and K
    rollout actors with CALLS_QUEUED collect calls each kept queued by `pump`."""

    def __init__(self, c: Config, k: int) -> None:
        import ray

        from relayrl.distributed.offpolicy import CALL_CHUNKS, CALLS_QUEUED
        from relayrl.distributed.server import ReplayServer
        from relayrl.distributed.workers import RolloutWorker, actor_name
        from relayrl.training.variables import VariableContainer

        self.ray, self.queued = ray, CALLS_QUEUED
        self.call_steps = CALL_CHUNKS * c.distributed.chunk_steps
        cfg = to_dict(c)
        obs_spec, act_spec = specs(c.env.id)
        names = f"bench-{uuid.uuid4().hex[:8]}"
        self.tmp = tempfile.TemporaryDirectory()
        self.server = ray.remote(num_cpus=0, max_concurrency=k + 8)(ReplayServer).options(
            name=actor_name(names, "replay")).remote(cfg, obs_spec, act_spec, self.tmp.name, max(k, 1))
        self.variables = ray.remote(num_cpus=0, max_concurrency=k + 8)(VariableContainer).options(
            name=actor_name(names, "variables")).remote(copy=True)
        worker = ray.remote(num_cpus=1, max_restarts=0)(RolloutWorker)
        path = [str(ROOT), *sys.path]
        self.workers = [worker.remote(cfg, i, names, path) for i in range(k)]
        ray.get([w.pid.remote() for w in self.workers])  # env and import errors surface here
        self.inflight: dict[Any, int] = {}

    def start(self) -> None:
        for i in range(len(self.workers)):
            for _ in range(self.queued):
                self._submit(i)

    def _submit(self, i: int) -> None:
        self.inflight[self.workers[i].collect.remote(self.call_steps, 0, True)] = i

    def pump(self, timeout: float) -> None:
        """Requeue the collect calls that finished (waiting up to `timeout` s for one)."""
        if not self.inflight:
            return
        ready, _ = self.ray.wait(list(self.inflight), num_returns=1, timeout=timeout)
        for ref in ready:
            i = self.inflight.pop(ref)
            self.ray.get(ref)  # an actor's error ends the benchmark
            self._submit(i)

    def shipped(self) -> list[int]:
        return list(self.ray.get(self.server.info.remote())["shipped"])

    def close(self) -> None:
        for h in [*self.workers, self.server, self.variables]:
            try:
                self.ray.kill(h, no_restart=True)
            except Exception:  # already gone
                pass
        self.tmp.cleanup()


def start_ray(num_cpus: int) -> Any:
    import ray

    ray.init(num_cpus=num_cpus, include_dashboard=False, logging_level="ERROR",
             object_store_memory=256 * 1024**2)
    return ray


# ---- part a: collection ---------------------------------------------------------------------
def collect_rate(env_id: str, k: int, warmup: float, seconds: float) -> float:
    """Env steps/s the server accepted from k actors. Each actor's rate is taken between the
    first and the last change of its `shipped` count in the window (a chunk lands at a time,
    so a plain total over the window would be off by up to a chunk per actor)."""
    cl = Cluster(bench_config(env_id, k), k)
    try:
        cl.start()
        t = time.perf_counter()
        while time.perf_counter() - t < warmup:
            cl.pump(0.05)
        prev = cl.shipped()
        first: list[tuple[float, int] | None] = [None] * k
        last: list[tuple[float, int] | None] = [None] * k
        t0 = time.perf_counter()
        # At least `seconds`, and longer (up to 10x) until two chunks of every actor have landed.
        while (now := time.perf_counter()) - t0 < seconds or (now - t0 < 10 * seconds and None in last):
            cl.pump(0.05)
            shipped = cl.shipped()
            for i in range(k):
                if shipped[i] != prev[i]:
                    if first[i] is None:
                        first[i] = (now, shipped[i])
                    else:
                        last[i] = (now, shipped[i])
            prev = shipped
        total = 0.0
        for start, end in zip(first, last, strict=True):
            if start is None or end is None:
                raise RuntimeError(f"fewer than two chunks of an actor landed in {10 * seconds:g} s")
            total += (end[1] - start[1]) / (end[0] - start[0])
        return total
    finally:
        cl.close()


def part_collect(args: argparse.Namespace) -> None:
    ray = start_ray(max(os.cpu_count() or 1, 2))
    try:
        print(f"\n### collect: env steps/s into the replay server (chunk 256 steps, {args.seconds:g} s after "
              f"{args.warmup:g} s warm-up; BusyEnv {args.step_ms:g} ms/step)\n")
        print("| env | K=1 steps/s | K=2 steps/s | K=2 / K=1 |")
        print("|---|---|---|---|")
        for name in args.envs:
            r1 = collect_rate(ENVS[name], 1, args.warmup, args.seconds)
            r2 = collect_rate(ENVS[name], 2, args.warmup, args.seconds)
            label = f"BusyEnv {args.step_ms:g} ms" if name == "busy" else MINITAUR
            print(f"| {label} | {r1:,.0f} | {r2:,.0f} | {r2 / r1:.2f} |", flush=True)
        print("\ntarget: K=2 / K=1 >= 1.70")
    finally:
        ray.shutdown()


# ---- part b: the learner ----------------------------------------------------------------------
def learner_alone(c: Config, steps: int, warm: int) -> float:
    obs_spec, act_spec = specs(c.env.id)  # the same network sizes as with actors
    agent = sac_agent(c, obs_spec, act_spec)
    with tempfile.TemporaryDirectory() as tmp:
        table, writer = build_replay(c, obs_spec, act_spec, Path(tmp))
        dims = (math.prod(obs_spec.shape), math.prod(act_spec.shape))
        for chunk in fake_chunks(EPISODE, *dims)[:max(1, -(-2 * c.replay.min_size_to_sample // EPISODE))]:
            writer.write_chunk(chunk)
        learner = Learner(agent, table, BATCH, torch.device("cpu"))
        learner.learn(warm)
        t0 = time.perf_counter()
        learner.learn(steps)
        return steps / (time.perf_counter() - t0)


def learner_with_actors(env_id: str, k: int, steps: int, warm: int) -> tuple[float, float]:
    """(grad steps/s, env steps/s the actors shipped while the learner ran: from the end of the
    fill, warm-up steps included; chunks land 256 steps at a time, so a short run reads coarse)."""
    from relayrl.distributed.remote import RemotePusher, RemoteTable

    c = bench_config(env_id, k)
    cl = Cluster(c, k)
    try:
        cl.start()
        while sum(cl.shipped()) < c.replay.min_size_to_sample:
            cl.pump(0.1)
        s0, start = sum(cl.shipped()), time.perf_counter()
        obs_spec, act_spec = specs(env_id)
        agent = sac_agent(c, obs_spec, act_spec)
        table = RemoteTable(cl.server, BATCH)
        pusher = RemotePusher(cl.variables, agent, c.distributed.push_interval)
        learner = Learner(agent, table, BATCH, torch.device("cpu"), variables=pusher)  # type: ignore[arg-type]

        def train(n: int) -> None:
            done = 0
            while done < n:
                cl.pump(0)
                ready = table.poll()
                if ready:
                    m = min(ready, n - done)
                    learner.learn(m)
                    done += m
                else:
                    cl.ray.wait([table.pending], timeout=0.05)

        train(warm)
        t0 = time.perf_counter()
        train(steps)
        end = time.perf_counter()
        return steps / (end - t0), (sum(cl.shipped()) - s0) / (end - start)
    finally:
        cl.close()


def part_learner(args: argparse.Namespace) -> None:
    torch.set_num_threads(1)  # the learner on one core, the actor on the other
    env_id = ENVS[args.env]
    c = bench_config(env_id, 1)
    before = learner_alone(c, args.grad_steps, args.grad_warmup)
    ray = start_ray(max(os.cpu_count() or 1, 2))
    try:
        rows = [(k, *learner_with_actors(env_id, k, args.grad_steps, args.grad_warmup)) for k in (1, 2)]
    finally:
        ray.shutdown()
    after = learner_alone(c, args.grad_steps, args.grad_warmup)  # again: the machine's speed drifts
    alone = (before + after) / 2
    label = f"BusyEnv {args.step_ms:g} ms" if args.env == "busy" else MINITAUR
    print(f"\n### learner: SAC (256, 256) batch 256 grad steps/s, torch threads 1, {args.grad_steps} timed steps "
          f"(actors' env: {label})\n")
    print("| learner | grad steps/s | / alone | actors' env steps/s meanwhile |")
    print("|---|---|---|---|")
    print(f"| alone: in-process Table, no weight pushes (before / after the rest) | {alone:,.0f} "
          f"({before:,.0f} / {after:,.0f}) | 1.00 | - |")
    for k, g, env_sps in rows:
        print(f"| RemoteTable + a weight push every 50 steps, K={k} actor{'s' if k > 1 else ''} collecting | "
              f"{g:,.0f} | {g / alone:.2f} | {env_sps:,.0f} |")
    print(f"\ntarget: K=1 >= 0.70 x alone ({os.cpu_count()} CPUs: K=2 leaves the learner no core of its own)")


# ---- part c: the replay server ---------------------------------------------------------------
OPS = ("ingest", "sample", "sample_np")


def numpy_batches(out: list[tuple[Any, Any]]) -> list[tuple[Any, Any]]:
    """Sampled batches with NumPy arrays in place of torch tensors (zero-copy views)."""
    # The server answers NumPy itself since 02cf508; tensors only from an in-process Table.
    return [(type(batch)(*(x.numpy() if isinstance(x, torch.Tensor) else x for x in batch)), info)
            for batch, info in out]


class MeteredServer:
    """Mixed into ReplayServer: the process's CPU seconds (every thread: the table's work and
    Ray's own RPC handling), an empty call, and `sample` answering with NumPy arrays (what
    Ray serialises without torch's pickling; not what ReplayServer does today)."""

    def cpu(self) -> float:
        return time.process_time()

    def noop(self) -> None:
        return None

    def sample_np(self, batch_size: int, max_batches: int, timeout: float) -> list[tuple[Any, Any]]:
        return numpy_batches(self.sample(batch_size, max_batches, timeout))  # type: ignore[attr-defined]


def op_args(op: str, b: int, index: int, token: str, chunks: list[StepChunk], i: int) -> tuple:
    return (index, token, chunks[i % len(chunks)]) if op == "ingest" else (b, 1, 1.0)


class BenchClient:
    """A Ray actor calling the server one call at a time, as a rollout actor's shipper does."""

    def __init__(self, server: Any, index: int, token: str, chunks: dict[int, list[StepChunk]]) -> None:
        self.server, self.index, self.token, self.chunks = server, index, token, chunks

    def run(self, op: str, b: int, seconds: float) -> tuple[int, float]:
        import ray

        method = getattr(self.server, op)
        calls, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            ray.get(method.remote(*op_args(op, b, self.index, self.token, self.chunks[b], calls)))
            calls += 1
        return calls, time.perf_counter() - t0


def timed(call: Any, seconds: float) -> tuple[int, float]:
    """(calls, elapsed) of calling `call(i)` for about `seconds`, after 3 warm-up calls."""
    for i in range(3):
        call(i)
    calls, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        call(calls)
        calls += 1
    return calls, time.perf_counter() - t0


def pickle_us(obj: Any, n: int = 300) -> tuple[float, float]:
    """(dumps, loads) us of pickle 5, Ray's serialiser for anything but NumPy buffers."""
    t0 = time.perf_counter()
    for _ in range(n):
        data = pickle.dumps(obj, protocol=5)
    t1 = time.perf_counter()
    for _ in range(n):
        pickle.loads(data)
    return 1e6 * (t1 - t0) / n, 1e6 * (time.perf_counter() - t1) / n


def part_server(args: argparse.Namespace) -> dict[str, float]:
    from relayrl.distributed.server import ReplayServer

    c = bench_config(BUSY, 2)
    cfg, (obs_spec, act_spec) = to_dict(c), specs(BUSY)
    tok = ["a", "b"]
    chunks = {b: fake_chunks(b) for b in args.batches}
    metered = type("Server", (MeteredServer, ReplayServer), {})
    res: dict[tuple[str, str, int], float] = {}  # (op, where, b) -> us per call (items/s follow)
    cpu: dict[tuple[str, int], float] = {}  # (op, b) -> server CPU us per call, driver as client
    ray = start_ray(max(os.cpu_count() or 1, 2))
    try:
        with tempfile.TemporaryDirectory() as tmp:
            local = metered(cfg, obs_spec, act_spec, tmp, 2)
            srv = ray.remote(num_cpus=0, max_concurrency=16)(metered).remote(cfg, obs_spec, act_spec, tmp, 2)
            for i, t in enumerate(tok):
                local.register(i, t)
            ray.get([srv.register.remote(i, t) for i, t in enumerate(tok)])
            cpu0 = ray.get(srv.cpu.remote())
            n, dt = timed(lambda i: ray.get(srv.noop.remote()), args.seconds)
            cpu["noop", 0] = 1e6 * (ray.get(srv.cpu.remote()) - cpu0) / (n + 4)
            res["noop", "driver", 0] = 1e6 * dt / n
            client = ray.remote(num_cpus=0)(BenchClient)
            clients = [client.remote(srv, i, t, chunks) for i, t in enumerate(tok)]
            for op in OPS:  # ingests first: the samples then come from a filled table
                for b in args.batches:
                    ch = chunks[b]
                    here, there = getattr(local, op), getattr(srv, op)
                    n, dt = timed(lambda i, f=here, o=op, b=b, ch=ch: f(*op_args(o, b, 0, "a", ch, i)), args.seconds)
                    res[op, "local", b] = 1e6 * dt / n
                    cpu0 = ray.get(srv.cpu.remote())
                    n, dt = timed(lambda i, f=there, o=op, b=b, ch=ch: ray.get(f.remote(*op_args(o, b, 0, "a", ch, i))),
                                  args.seconds)
                    cpu[op, b] = 1e6 * (ray.get(srv.cpu.remote()) - cpu0) / (n + 4)
                    res[op, "driver", b] = 1e6 * dt / n
                    both = ray.get([cl.run.remote(op, b, args.seconds) for cl in clients])
                    res[op, "2 clients", b] = 1e6 * max(d for _, d in both) / sum(k for k, _ in both)
            batch = local.sample(BATCH, 1, 1.0)[0]
    finally:
        ray.shutdown()
    print(f"\n### server: ReplayServer throughput ({args.seconds:g} s per figure; obs {OBS} float32, act {ACT}; "
          f"sample and sample_np both answer NumPy arrays since commit 02cf508)\n")
    print("| op | b | in-process items/s (us/call) | Ray from driver items/s (us/call) | in-process / Ray "
          "| Ray, 2 client actors items/s | server CPU us/call (Ray) |")
    print("|---|---|---|---|---|---|---|")
    print(f"| noop | - | - | ({res['noop', 'driver', 0]:,.0f}) | - | - | {cpu['noop', 0]:,.0f} |")
    for op in OPS:
        for b in args.batches:
            lo_us, ray_us, two_us = res[op, "local", b], res[op, "driver", b], res[op, "2 clients", b]
            print(f"| {op} | {b} | {1e6 * b / lo_us:,.0f} ({lo_us:,.0f}) | {1e6 * b / ray_us:,.0f} ({ray_us:,.0f}) | "
                  f"{ray_us / lo_us:.1f} | {1e6 * b / two_us:,.0f} | {cpu[op, b]:,.0f} |")
    batch_np, info = numpy_batches([batch])[0]
    batch_torch = type(batch_np)(*(torch.from_numpy(x) if isinstance(x, np.ndarray) else x for x in batch_np))
    torch_d, torch_l = pickle_us((batch_torch, info))
    np_d, np_l = pickle_us((batch_np, info))
    print(f"\npickle 5 of one sampled batch of {BATCH}: torch tensors {torch_d:,.0f} us dumps + {torch_l:,.0f} us "
          f"loads; as NumPy {np_d:,.0f} + {np_l:,.0f} us")
    # The model's constants: server CPU per call = rpc (an empty call) + fixed work + b x per-item
    # work; the per-item slopes from the in-process figures (less noisy), the rest from the Ray ones.
    lo, hi = min(args.batches), max(args.batches)
    rpc = cpu["noop", 0]
    fit = {"rpc_us": rpc, "rtt_us": res["noop", "driver", 0], "recv_us": np_l}  # the learner unpickles NumPy
    for op, fixed, item in (("ingest", "chunk_us", "ingest_us"), ("sample", "batch_us", "sample_us"),
                            ("sample_np", "batch_np_us", None)):
        slope = (res[op, "local", hi] - res[op, "local", lo]) / (hi - lo) if hi > lo else 0.0
        fit[fixed] = max(0.0, cpu[op, lo] - rpc - lo * max(slope, 0.0))
        if item:
            fit[item] = max(slope, 0.0)
    print("fitted for --part simulate: " + " ".join(f"--{k.replace('_', '-')} {fit[k]:.3g}" for k in
                                                     ("rpc_us", "chunk_us", "ingest_us", "batch_us", "sample_us",
                                                      "recv_us", "rtt_us")))
    fit["recv_np_us"] = np_l
    print(f"with NumPy batches (--numpy-batches): batch_us {fit['batch_np_us']:.3g}, recv_us {np_l:.3g}")
    return fit


# ---- part d: bytes and the model ----------------------------------------------------------------
def wire_bytes() -> dict[str, int]:
    """Pickled sizes (Ray's serialisation is pickle 5; out-of-band buffers cost the same bytes)."""
    from relayrl.replay.writers import stack_steps
    from relayrl.types import Transition

    c = bench_config(BUSY, 1)
    obs_spec, act_spec = specs(BUSY)
    steps = [Transition(torch.randn(1, OBS), torch.rand(1, ACT), torch.randn(1), torch.randn(1, OBS),
                        torch.zeros(1, dtype=torch.bool), torch.zeros(1, dtype=torch.bool)) for _ in range(256)]
    chunk = stack_steps(steps)
    with tempfile.TemporaryDirectory() as tmp:
        table, writer = build_replay(c, obs_spec, act_spec, Path(tmp))
        for ch in fake_chunks(EPISODE)[:2]:
            writer.write_chunk(ch)
        group = [table.sample(BATCH) for _ in range(16)]  # distinct batches: pickle would share repeats
    agent = sac_agent(c, obs_spec, act_spec)
    weights = [p.detach() for p in agent.policy_network().parameters()]

    def size(x: Any) -> int:
        return len(pickle.dumps(x, protocol=5))

    return {"chunk": size(chunk), "batch": size(group[0]), "group": size(group),
            "weights": size(weights), "weight_params": sum(w.numel() for w in weights)}


@dataclass
class Model:
    """A steady-state bottleneck model of the distributed run (docs/distributed.md). Times in
    us unless named otherwise; server figures are CPU time in the server process. Defaults:
    measured by `--part server` on the shared 2-core machine (docs/benchmarks.md), except the
    env, the learner and the NIC, which are scenario choices."""

    env_ms: float = 3.7  # one env step of one actor (Minitaur: ~3.7 ms on this CPU)
    actor_ms: float = 0.2  # the actor's own cost per step (policy, observers, stacking, shipping)
    chunk: int = 256  # env steps per insert RPC (distributed.chunk_steps)
    rpc_us: float = 750.0  # server CPU per RPC: Ray's own handling (an empty call)
    chunk_us: float = 1200.0  # server work per insert call besides the RPC and the steps
    ingest_us: float = 1.9  # server work per env step ingested
    batch_us: float = 2200.0  # server work per sampled batch besides its items (incl. pickling tensors)
    sample_us: float = 0.27  # server work per item sampled
    recv_us: float = 1100.0  # the learner's time to take in one batch (unpickling torch tensors)
    rtt_us: float = 1440.0  # client-observed round trip of an empty call
    learner_sps: float = 1000.0  # gradient steps/s with batches ready: an assumed GPU learner (one CPU thread: 38)
    batch: int = BATCH
    group: int = 16  # batches per sample RPC (RemoteTable.max_batches)
    spi: float = 256.0  # samples per insert: 256 = one batch-256 gradient step per env step (SAC 1:1)
    step_bytes: float = 120.0  # ingest bytes per env step (pickled chunk / chunk steps)
    item_bytes: float = 250.0  # sampled bytes per item (pickled batch / batch size)
    weight_bytes: float = 300_000.0  # one weight pull
    pull_interval: int = 1000  # env steps between an actor's pulls
    gbps: float = 10.0  # each machine's NIC, per direction

    def predict(self, k: int, shards: int) -> dict[str, Any]:
        ups = self.spi / self.batch  # gradient steps per env step, held by the rate limiter
        a = 1000.0 / (self.env_ms + self.actor_ms)  # one actor's env steps/s
        ingest_svc = self.rpc_us + self.chunk_us + self.chunk * self.ingest_us  # server CPU per insert RPC
        sample_svc = self.rpc_us + self.group * (self.batch_us + self.batch * self.sample_us)  # per sample RPC
        per_step = ingest_svc / self.chunk + ups * sample_svc / self.group  # server CPU us per env step
        server_cap = shards * 1e6 / per_step  # one core per shard: a Python process, one GIL
        step_s = 1 / self.learner_sps + self.recv_us * 1e-6  # learner time per gradient step
        bw = self.gbps * 1e9 / 8
        # Each shard's NIC: chunks in, samples out; the learner's: samples in, weight pulls out
        # (the variable container lives beside the learner). As if every shard had a machine of
        # its own: one server beside the learner keeps its samples off the wire.
        shard_bytes = max(self.step_bytes, self.spi * self.item_bytes) / shards
        learner_bytes = max(self.spi * self.item_bytes, self.weight_bytes / self.pull_interval)
        net_cap = bw / max(shard_bytes, learner_bytes)

        def caps(r: float) -> list[tuple[float, str]]:
            # The server's threads share one GIL (processor sharing): a request's service stretches
            # by 1 / (1 - load of the other traffic). An actor stalls when its one insert in flight
            # takes longer than collecting the next chunk; the learner when its sample requests
            # (one in flight per shard) take longer than training on the groups before them.
            # Both stalls are the server's doing, and named so.
            ingest_load = r * ingest_svc / self.chunk * 1e-6 / shards
            sample_load = r * ups * sample_svc / self.group * 1e-6 / shards
            ins = (self.rtt_us + ingest_svc / max(1 - sample_load, 1e-3)) * 1e-6
            smp = (self.rtt_us + sample_svc / max(1 - ingest_load, 1e-3)) * 1e-6
            collect, train = self.chunk / a, self.group * step_s
            return [(k * self.chunk / max(collect, ins), "env" if collect >= ins else "server"),
                    (self.group / max(train, smp / shards) / ups, "learner" if train >= smp / shards else "server"),
                    (server_cap, "server"), (net_cap, "network")]

        lo, hi = 0.0, min(caps(0.0))[0]
        for _ in range(60):  # the largest rate r that every capacity at load r allows (they fall as r rises)
            mid = (lo + hi) / 2
            lo, hi = (mid, hi) if min(caps(mid))[0] >= mid else (lo, mid)
        return {"K": k, "S": shards, "env_sps": lo, "grad_sps": lo * ups, "learner_util": lo * ups / self.learner_sps,
                "server_util": lo / server_cap, "net_util": lo / net_cap, "bound": min(caps(lo))[1]}


# Model.batch_us and Model.recv_us when the server answers NumPy arrays (measured as sample_np).
NUMPY_BATCH_US, NUMPY_RECV_US = 1300.0, 51.0
MODEL_FLAGS = ("env_ms", "actor_ms", "rpc_us", "chunk_us", "ingest_us", "batch_us", "sample_us", "recv_us", "rtt_us",
               "learner_sps", "spi", "gbps", "pull_interval", "step_bytes", "item_bytes")


def part_simulate(args: argparse.Namespace, fit: dict[str, float] | None = None) -> None:
    sizes = wire_bytes()
    print("\n### bytes on the wire: SAC (256, 256), obs 24 float32, act 4 (pickle 5, what Ray ships)\n")
    print("| message | bytes | per |")
    print("|---|---|---|")
    print(f"| insert: StepChunk of 256 env steps | {sizes['chunk']:,} | {sizes['chunk'] / 256:.0f} B per env step |")
    print(f"| sample: one batch of {BATCH} (Batch + SampleInfo) | {sizes['batch']:,} | "
          f"{sizes['batch'] / BATCH:.0f} B per item |")
    print(f"| sample RPC: a group of 16 batches | {sizes['group']:,} | one RemoteTable request |")
    print(f"| weights: policy network ({sizes['weight_params']:,} float32) | {sizes['weights']:,} | "
          f"a push (every 50 grad steps) or an actor's pull (every 1000 env steps) |")
    m = Model(step_bytes=sizes["chunk"] / 256, item_bytes=sizes["batch"] / BATCH, weight_bytes=sizes["weights"])
    over = dict(fit or {})  # measured in this run by the server part
    if args.numpy_batches:  # the server answering NumPy arrays (a proposed change, measured as sample_np)
        over["batch_us"] = over.pop("batch_np_us", NUMPY_BATCH_US)
        over["recv_us"] = over.pop("recv_np_us", NUMPY_RECV_US)
    over.update({k: getattr(args, k) for k in MODEL_FLAGS if getattr(args, k) is not None})
    m = replace(m, **{k: v for k, v in over.items() if k in MODEL_FLAGS})
    print(f"\n### model (not a measurement): {', '.join(f'{k}={getattr(m, k):g}' for k in MODEL_FLAGS)}, "
          f"chunk={m.chunk}, group={m.group}x{m.batch}")
    for shards in sorted({1, args.shards}):
        print(f"\nS = {shards} replay shard{'s' if shards > 1 else ''}:\n")
        print("| K | env steps/s | grad steps/s | learner util | server util (per shard) | NIC util | bound |")
        print("|---|---|---|---|---|---|---|")
        for k in args.actors:
            p = m.predict(k, shards)
            print(f"| {k} | {p['env_sps']:,.0f} | {p['grad_sps']:,.0f} | {p['learner_util']:.0%} | "
                  f"{p['server_util']:.0%} | {p['net_util']:.1%} | {p['bound']} |")


# ---- command line ----------------------------------------------------------------------------
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", choices=["collect", "learner", "server", "simulate", "all"], default="all")
    ap.add_argument("--quick", action="store_true", help="a smoke run of a few seconds per part")
    ap.add_argument("--step-ms", type=float, default=3.7, help="BusyEnv's CPU cost per step")
    ap.add_argument("--envs", nargs="+", choices=list(ENVS), default=["busy", "minitaur"], help="collect part")
    ap.add_argument("--seconds", type=float, help="timing per figure (collect: 8, server: 1)")
    ap.add_argument("--warmup", type=float, default=3.0, help="collect: seconds before timing")
    ap.add_argument("--env", choices=list(ENVS), default="busy", help="learner part: the actors' env")
    ap.add_argument("--grad-steps", type=int, default=600, help="learner: timed gradient steps")
    ap.add_argument("--grad-warmup", type=int, default=100)
    ap.add_argument("--worker-niceness", type=int,
                    help="nice value of Ray's worker processes (Ray's default: 15; the driver, where the learner "
                         "runs, stays at 0)")
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 32, 256], help="server: items per call")
    ap.add_argument("--actors", type=int, nargs="+", default=[1, 2, 4, 8, 16, 32, 64], help="simulate: K")
    ap.add_argument("--shards", type=int, default=4, help="simulate: S replay shards")
    for name in MODEL_FLAGS:
        flag = name.replace("_", "-")
        ap.add_argument(f"--{flag}", type=int if name == "pull_interval" else float, help=f"simulate: Model.{name}")
    ap.add_argument("--numpy-batches", action="store_true",
                    help="simulate: the server answering NumPy arrays instead of torch tensors (proposed)")
    args = ap.parse_args()
    if args.quick:
        args.warmup, args.grad_steps, args.grad_warmup = 1.0, 100, 10
    os.environ[STEP_MS_VAR] = str(args.step_ms)  # before ray.init: the actors' BusyEnv reads it
    if args.worker_niceness is not None:  # read by the raylet that ray.init starts
        os.environ["RAY_worker_niceness"] = str(args.worker_niceness)
    print(machine() + f" | Ray worker niceness {os.environ.get('RAY_worker_niceness', '15 (default)')}")
    parts = ["collect", "learner", "server", "simulate"] if args.part == "all" else [args.part]
    fit = None
    for part in parts:
        a = argparse.Namespace(**vars(args))
        if a.seconds is None:
            a.seconds = {"collect": 3.0 if args.quick else 8.0, "server": 0.3 if args.quick else 1.0}.get(part, 0.0)
        if part == "collect":
            part_collect(a)
        elif part == "learner":
            part_learner(a)
        elif part == "server":
            fit = part_server(a)
        else:
            part_simulate(a, fit)


if __name__ == "__main__":
    main()
