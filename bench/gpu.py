"""Every figure of the GPU table (issue 34) in one run, for relayrl and for the eager floor, in
at most ~8 minutes on one GPU; or, with --smoke, a train / evaluate / export / load check of
every algorithm on the device.

    python bench/gpu.py [--device cuda] [--seconds 40] [--out gpu.json]
    python bench/gpu.py --smoke [--device cuda] [--steps 300]
    python bench/gpu.py --profile ddqn-pong [--device cuda] [--seconds 10]
    python bench/gpu.py --syncs ppo-stateless-pendulum ddqn-pong [--seconds 5]

Figures (env steps/s over the steady part of each run: from the first log row after learning
starts to the last, evaluations excluded; each run capped by steps and by --seconds):
- ddqn-pong at its own ratio (one env, a gradient step every 4 env steps), and at the same
  ratio with its 4 env steps taken by 4 ale-py vector envs at once; dqn-pong-fast (8 ale-py
  vector envs, 2 gradient steps of 128 per 8 env steps);
- sac-pendulum (one env step + one gradient step), sac-batched (32 copies, 16 gradient steps
  per batched step), ppo-stateless-pendulum (the whole loop), dqn-cartpole-fast (on --device and
  on the CPU, same run);
- eager floors in bare PyTorch: a Nature-CNN Double DQN update at batch 32 and a batch-1 action
  (ms), the Pong env's own step, and what they allow the ddqn-pong loop (4 actions, 4 env steps
  and one update per 4 env steps); a SAC update at batch 256 and a batch-1 action (ms), and the
  sac-pendulum loop they allow. Device times are taken with torch.cuda.synchronize on CUDA;
- on CUDA, the runs of GRAPH_AB once more with RELAYRL_CUDA_GRAPHS=0 (gradient steps launched
  kernel by kernel instead of replayed from a CUDA graph), those of COMPILE_AB with
  RELAYRL_COMPILE=1 (their losses through torch.compile inside the graphs; the figure counts from
  the first log row after learning starts, so it leaves the compiling out, which the run's
  `wall_s` keeps), and those of REPLAY_AB with their replay where replay.device = "auto" does
  not put it, in the same process.

The table goes to stdout and the figures to a JSON file (--out; default $OUT/gpu.json when OUT
is set, else gpu.json). docs/benchmarks.md ("GPU figures") says how to run it on a lent GPU.
"""

from __future__ import annotations

import argparse
import copy
import importlib.util
import json
import os
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

# (name, preset, overrides, total env steps at most): the table, with the fast Pong preset,
# then ddqn-pong's ratio on 4 envs.
RUNS: list[tuple[str, str, list[str], int]] = [
    ("ddqn-pong", "ddqn-pong", ["train.initial_collect_steps=2000", "eval.episodes=1"], 100_000),
    ("dqn-pong-fast", "dqn-pong-fast", ["train.initial_collect_steps=4000", "eval.episodes=1"], 200_000),
    ("sac-pendulum", "sac-pendulum", ["eval.episodes=1"], 20_000),
    ("sac-batched", "sac-batched", ["eval.episodes=1"], 40_000),
    ("ppo-stateless-pendulum", "ppo-stateless-pendulum", ["eval.episodes=32"], 1_500_000),
    ("dqn-cartpole-fast", "dqn-cartpole-fast", ["eval.episodes=1"], 50_000),
    # ddqn-pong's ratio (a gradient step of 32 per 4 env steps) with its 4 env steps taken by 4
    # ale-py copies at once: one env's emulator step (~0.9 ms) caps the preset near 1,090 env
    # steps/s. Last, so that a table cut short by its time limit loses this run first.
    ("ddqn-pong-4ale", "ddqn-pong", ["env.num_envs=4", "env.vectorization=ale", "train.initial_collect_steps=2000",
                                     "eval.episodes=1"], 100_000),
]
LOG_ROWS = 20  # log rows per run: the seconds cap is checked at each
# On CUDA these also run with RELAYRL_CUDA_GRAPHS=0 (every kernel launched one by one), same process:
# what capturing the gradient step in a CUDA graph buys.
GRAPH_AB = ("ddqn-pong", "sac-pendulum", "sac-batched", "ppo-stateless-pendulum", "dqn-cartpole-fast")
# On CUDA these also run with their replay where replay.device = "auto" does not put it (image
# runs' frames in host memory, vector observations on the GPU): what auto's choice buys.
# On CUDA these also run with RELAYRL_COMPILE=1 (nn/graphed.py: losses through torch.compile).
COMPILE_AB = ("ppo-stateless-pendulum", "sac-pendulum")
REPLAY_AB = {"ddqn-pong": "numpy", "dqn-pong-fast": "numpy", "sac-pendulum": "cuda"}


def fail(message: str) -> None:
    """Bad input: one line and exit code 2."""
    print(f"bench/gpu.py: {message}", file=sys.stderr)
    raise SystemExit(2)


def check_device(name: str) -> torch.device:
    try:
        device = torch.device(name)
    except RuntimeError:
        fail(f"--device {name!r} is not a torch device; valid: cuda, cuda:N, cpu")
    if device.type not in ("cuda", "cpu"):
        fail(f"--device {name!r} is not valid; valid: cuda, cuda:N, cpu")
    if device.type == "cuda" and not torch.cuda.is_available():
        fail("--device cuda: torch sees no CUDA device here (pass --device cpu to run on the CPU)")
    return device


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def ms_per_call(fn: Callable[[], Any], device: torch.device, seconds: float = 2.0) -> float:
    """Median milliseconds per call over batches of calls, after a warm-up."""
    for _ in range(5):
        fn()
    sync(device)
    times: list[float] = []
    end = time.perf_counter() + seconds
    while time.perf_counter() < end or len(times) < 3:
        t0 = time.perf_counter()
        for _ in range(20):
            fn()
        sync(device)
        times.append((time.perf_counter() - t0) / 20 * 1e3)
    return float(np.median(times))


# ---- relayrl runs -------------------------------------------------------------------------

def timed_run(preset: str, overrides: list[str], device: torch.device, seconds: float,
              steps: int) -> dict[str, Any]:
    """Train `preset` on `device` for at most `steps` env steps / `seconds` of steady running;
    env steps/s between the first log row after learning starts and the last."""
    import relayrl
    from relayrl.presets import load_config

    config = load_config(preset, overrides)
    total = min(steps, config.train.total_steps)
    start = min(config.train.initial_collect_steps, total // 4)  # learning starts within the run
    config.train.initial_collect_steps = start
    config.train.total_steps = total
    config.train.log_interval = max(1, (total - start) // LOG_ROWS)
    # Evaluations at the start and after the loop only (the final one comes after the last
    # log row): an interval of `total` would fire before the log row at `total`.
    config.eval.interval = total + 1
    config.train.checkpoint_interval = 0
    config.train.policy_save_interval = 0
    config.device = str(device)
    points: list[tuple[int, float]] = []

    def watch(row: dict[str, Any]) -> bool:
        if row.get("event") == "log" and row["step"] > start:
            points.append((row["step"], time.perf_counter()))
        # a seconds cap: stop (cleanly) once the steady window is long enough
        return not points or time.perf_counter() - points[0][1] < seconds

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        result = relayrl.train(config, Path(tmp) / "run", progress=False, callbacks=[watch])
    wall = time.perf_counter() - t0
    out: dict[str, Any] = {"preset": preset, "device": str(device), "wall_s": round(wall, 1),
                           "final_return": result.final.get("average_return")}
    if len(points) >= 2:
        (s0, t_0), (s1, t_1) = points[0], points[-1]
        out.update(env_steps_per_s=round((s1 - s0) / (t_1 - t_0), 1), window_steps=s1 - s0)
    else:  # too short a run for two log rows after learning starts
        out.update(env_steps_per_s=None, window_steps=0)
    return out


# ---- eager floors in bare PyTorch ---------------------------------------------------------

def nature_cnn(actions: int) -> nn.Module:
    """Mnih et al. 2015's Q-network, scaling uint8 frames by 1/255 itself."""
    return nn.Sequential(
        nn.Conv2d(4, 32, 8, 4), nn.ReLU(), nn.Conv2d(32, 64, 4, 2), nn.ReLU(), nn.Conv2d(64, 64, 3, 1), nn.ReLU(),
        nn.Flatten(), nn.Linear(3136, 512), nn.ReLU(), nn.Linear(512, actions))


def pong_floor(device: torch.device) -> dict[str, Any]:
    """A bare eager Double DQN update (Nature CNN, batch 32, Adam, Huber, clip 10) and a batch-1
    greedy action, plus one Pong env step (the Gymnasium path, one env)."""
    online, target = nature_cnn(6).to(device), nature_cnn(6).to(device)
    target.load_state_dict(online.state_dict())
    opt = torch.optim.Adam(online.parameters(), lr=1e-4)
    b = 32
    obs = torch.randint(0, 256, (b, 4, 84, 84), dtype=torch.uint8, device=device)
    nobs = torch.randint(0, 256, (b, 4, 84, 84), dtype=torch.uint8, device=device)
    act = torch.randint(0, 6, (b, 1), device=device)
    rew, disc = torch.randn(b, device=device), torch.full((b,), 0.99, device=device)

    def update() -> None:
        with torch.no_grad():
            best = online(nobs.float() / 255).argmax(1, keepdim=True)
            y = rew + disc * target(nobs.float() / 255).gather(1, best).squeeze(1)
        q = online(obs.float() / 255).gather(1, act).squeeze(1)
        loss = F.smooth_l1_loss(q, y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(online.parameters(), 10.0)
        opt.step()

    one = torch.randint(0, 256, (1, 4, 84, 84), dtype=torch.uint8)

    def action() -> None:
        with torch.no_grad():
            online(one.to(device, non_blocking=True).float() / 255).argmax(1).cpu()

    out = {"dqn_update_b32_ms": ms_per_call(update, device), "action_b1_ms": ms_per_call(action, device)}
    try:
        from relayrl.envs import make_env

        env = make_env("relayrl/Atari-Pong-v0", 1)
        env.reset(seed=0)
        zero = torch.zeros(1, dtype=torch.int64)
        out["pong_env_step_ms"] = ms_per_call(lambda: env.step(zero), torch.device("cpu"))
        env.close()
    except Exception as e:  # ale-py missing: the floor without the env's cost
        out["pong_env_step_ms"] = 0.0
        out["pong_env_note"] = f"{type(e).__name__}: {e}"
    per_4 = 4 * (out["action_b1_ms"] + out["pong_env_step_ms"]) + out["dqn_update_b32_ms"]
    out["ddqn_pong_loop_env_steps_per_s"] = round(4 / per_4 * 1e3, 1)
    return {k: round(v, 3) if isinstance(v, float) else v for k, v in out.items()}


def mlp(sizes: list[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for a, b in zip(sizes[:-2], sizes[1:-1], strict=True):
        layers += [nn.Linear(a, b), nn.ReLU()]
    return nn.Sequential(*layers, nn.Linear(sizes[-2], sizes[-1]))


def sac_floor(device: torch.device) -> dict[str, Any]:
    """A bare eager SAC update as CleanRL writes it (256x256 actor and twin critics, batch 256,
    automatic entropy, Polyak targets) and a batch-1 action, plus one Pendulum-v1 step."""
    import gymnasium as gym

    o, a, b = 3, 1, 256
    actor = mlp([o, 256, 256, 2 * a]).to(device)
    q1, q2 = mlp([o + a, 256, 256, 1]).to(device), mlp([o + a, 256, 256, 1]).to(device)
    t1, t2 = copy.deepcopy(q1), copy.deepcopy(q2)
    log_alpha = torch.zeros(1, device=device, requires_grad=True)
    q_opt = torch.optim.Adam([*q1.parameters(), *q2.parameters()], lr=3e-4)
    pi_opt = torch.optim.Adam(actor.parameters(), lr=3e-4)
    a_opt = torch.optim.Adam([log_alpha], lr=3e-4)
    obs, nobs = torch.randn(b, o, device=device), torch.randn(b, o, device=device)
    act = torch.rand(b, a, device=device) * 2 - 1
    rew, done = torch.randn(b, device=device), torch.zeros(b, device=device)

    def sample(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, log_std = actor(x).chunk(2, dim=-1)
        std = log_std.clamp(-5, 2).exp()
        u = mean + std * torch.randn_like(mean)
        y = torch.tanh(u)
        logp = (-0.5 * ((u - mean) / std) ** 2 - std.log() - 0.9189385).sum(-1) - torch.log(1 - y**2 + 1e-6).sum(-1)
        return y, logp

    def update() -> None:
        alpha = log_alpha.exp().detach()
        with torch.no_grad():
            na, nlogp = sample(nobs)
            x = torch.cat([nobs, na], -1)
            y = rew + 0.99 * (1 - done) * (torch.min(t1(x), t2(x)).squeeze(-1) - alpha * nlogp)
        x = torch.cat([obs, act], -1)
        q_loss = F.mse_loss(q1(x).squeeze(-1), y) + F.mse_loss(q2(x).squeeze(-1), y)
        q_opt.zero_grad(set_to_none=True)
        q_loss.backward()
        q_opt.step()
        pa, logp = sample(obs)
        x = torch.cat([obs, pa], -1)
        pi_loss = (alpha * logp - torch.min(q1(x), q2(x)).squeeze(-1)).mean()
        pi_opt.zero_grad(set_to_none=True)
        pi_loss.backward()
        pi_opt.step()
        a_loss = -(log_alpha.exp() * (logp.detach() - a)).mean()
        a_opt.zero_grad(set_to_none=True)
        a_loss.backward()
        a_opt.step()
        with torch.no_grad():
            for net, tgt in ((q1, t1), (q2, t2)):
                torch._foreach_lerp_(list(tgt.parameters()), list(net.parameters()), 0.005)

    one = torch.randn(1, o)

    def action() -> None:
        with torch.no_grad():
            sample(one.to(device, non_blocking=True))[0].cpu()

    env = gym.make("Pendulum-v1")
    env.reset(seed=0)
    zero = np.zeros(1, np.float32)

    def env_step() -> None:
        env.step(zero)

    out = {"sac_update_b256_ms": ms_per_call(update, device), "sac_action_b1_ms": ms_per_call(action, device),
           "pendulum_env_step_ms": ms_per_call(env_step, torch.device("cpu"), 0.5)}
    env.close()
    per_step = out["sac_update_b256_ms"] + out["sac_action_b1_ms"] + out["pendulum_env_step_ms"]
    out["sac_pendulum_loop_env_steps_per_s"] = round(1 / per_step * 1e3, 1)
    return {k: round(v, 3) for k, v in out.items()}


def variants(name: str, device: torch.device) -> list[tuple[str, torch.device, dict[str, str], list[str]]]:
    """(key, device, environment settings, extra overrides) for each timed run of `name`."""
    base = {"RELAYRL_CUDA_GRAPHS": "1", "RELAYRL_COMPILE": "0"}
    out: list[tuple[str, torch.device, dict[str, str], list[str]]] = [(name, device, base, [])]
    if device.type == "cuda" and name in GRAPH_AB:
        out.append((f"{name}@no-graphs", device, {**base, "RELAYRL_CUDA_GRAPHS": "0"}, []))
    if device.type == "cuda" and name in COMPILE_AB:
        out.append((f"{name}@compiled", device, {**base, "RELAYRL_COMPILE": "1"}, []))
    if device.type == "cuda" and name in REPLAY_AB:
        where = REPLAY_AB[name]
        out.append((f"{name}@replay.device={where}", device, base, [f"replay.device={where}"]))
    if device.type == "cuda" and name == "dqn-cartpole-fast":
        out.append((f"{name}@cpu", torch.device("cpu"), base, []))
    return out


def bench(device: torch.device, seconds: float, out: Path, max_steps: int = 0,
          only: list[str] | None = None) -> dict[str, Any]:
    """Every figure; `out` is rewritten after each run, so a run cut short keeps what it measured.
    `only`: these runs, on `device` alone, and no floors (an A/B of two source trees)."""
    figures: dict[str, Any] = {"device": str(device), "gpu": torch.cuda.get_device_name(device)
                               if device.type == "cuda" else None, "torch": torch.__version__, "runs": {}}
    for name, preset, overrides, steps in RUNS:
        if only and name not in only:
            continue
        for key, dev, settings, extra in variants(name, device)[:1] if only else variants(name, device):
            t0 = time.perf_counter()
            before = {k: os.environ.get(k) for k in settings}
            if not only:  # an --only run keeps the caller's settings
                os.environ.update(settings)
            try:
                cap = min(steps, max_steps) if max_steps else steps
                figures["runs"][key] = timed_run(preset, [*overrides, *extra], dev, seconds, cap)
            except Exception as e:  # one broken run leaves the others' figures
                figures["runs"][key] = {"error": f"{type(e).__name__}: {e}"}
                traceback.print_exc()
            finally:
                for k, v in before.items():
                    if v is None:
                        os.environ.pop(k, None)
                    else:
                        os.environ[k] = v
            print(f"  {key}: {figures['runs'][key]} ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
            out.write_text(json.dumps(figures, indent=1) + "\n")
    if not only:
        figures["floor"] = {**pong_floor(device), **sac_floor(device)}
        out.write_text(json.dumps(figures, indent=1) + "\n")
    return figures


def profile(name: str, device: torch.device, seconds: float, out: Path) -> None:
    """One run of `name` under cProfile; the 40 functions with the most own time go to `out`."""
    import cProfile
    import io
    import pstats

    preset, overrides, steps = next((p, o, s) for n, p, o, s in RUNS if n == name)
    prof = cProfile.Profile()
    prof.enable()
    figures = timed_run(preset, overrides, device, seconds, steps)
    prof.disable()
    text = io.StringIO()
    pstats.Stats(prof, stream=text).sort_stats("tottime").print_stats(40)
    out.write_text(f"{name} on {device}: {figures}\n{text.getvalue()}")
    print(f"profile of {name}: {out}")


def syncs(names: list[str], device: torch.device, seconds: float, out: Path) -> None:
    """Where each run waits for the GPU: runs `names` under `torch.cuda.set_sync_debug_mode("warn")`
    and counts the host syncs by the relayrl lines that caused them (the innermost three frames
    in src/ or bench/); the counts per run go to `out`."""
    import collections
    import traceback as tb
    import warnings

    if device.type != "cuda":
        fail("--syncs needs a CUDA device (host syncs exist only there)")
    lines: list[str] = []
    for name in names:
        preset, overrides, steps = next((p, o, s) for n, p, o, s in RUNS if n == name)
        counts: collections.Counter[str] = collections.Counter()
        shown = warnings.showwarning

        def record(message: Any, category: Any, filename: str, lineno: int, file: Any = None,
                   line: Any = None, shown: Any = shown, counts: Any = counts) -> None:
            if "synchroniz" not in str(message):
                return shown(message, category, filename, lineno, file, line)
            frames = [f for f in tb.extract_stack()[:-1] if "/src/relayrl/" in f.filename or "/bench/" in f.filename]
            counts[" < ".join(f"{Path(f.filename).name}:{f.lineno}" for f in frames[-3:][::-1])] += 1

        with warnings.catch_warnings():
            warnings.simplefilter("always")
            warnings.showwarning = record
            torch.cuda.set_sync_debug_mode("warn")
            try:
                figures = timed_run(preset, overrides, device, seconds, steps)
            finally:
                torch.cuda.set_sync_debug_mode("default")
                warnings.showwarning = shown
        lines.append(f"{name}: {figures}; {sum(counts.values())} host syncs")
        lines += [f"  {n:7d}  {where}" for where, n in counts.most_common(25)]
    out.write_text("\n".join(lines) + "\n")
    print(f"host syncs: {out}")


def table(figures: dict[str, Any]) -> str:
    runs, floor = figures["runs"], figures["floor"]

    def sps(key: str) -> str:
        r = runs.get(key, {})
        if not r:
            return "not run"
        if "error" in r:
            return "error: " + r["error"][:60]
        if not r.get("env_steps_per_s"):
            return "not measured (run too short)"
        return f"{r['env_steps_per_s']:,.0f} env steps/s"

    def graphs(key: str) -> str:
        out = f"; without CUDA graphs {sps(key + '@no-graphs')}" if key + "@no-graphs" in runs else ""
        out += f"; losses compiled {sps(key + '@compiled')}" if key + "@compiled" in runs else ""
        other = next((k for k in runs if k.startswith(key + "@replay.device=")), None)
        return out + (f"; {other.split('@')[1]} {sps(other)}" if other else "")

    rows = [
        ("ddqn-pong (1 env, 1 gradient step / 4 env steps)", sps("ddqn-pong") + graphs("ddqn-pong"),
         f"eager floor {floor['ddqn_pong_loop_env_steps_per_s']:,.0f} env steps/s (update b32 "
         f"{floor['dqn_update_b32_ms']:.2f} ms, action b1 {floor['action_b1_ms']:.3f} ms, "
         f"env step {floor['pong_env_step_ms']:.3f} ms)"),
        ("ddqn-pong's ratio on 4 ale-py envs (1 gradient step / 4 env steps)", sps("ddqn-pong-4ale"), "-"),
        ("dqn-pong-fast (8 ale-py envs, 2 x b128 / 8 env steps)", sps("dqn-pong-fast") + graphs("dqn-pong-fast"), "-"),
        ("sac-pendulum (1 env step + 1 gradient step)", sps("sac-pendulum") + graphs("sac-pendulum"),
         f"eager floor {floor['sac_pendulum_loop_env_steps_per_s']:,.0f} env steps/s (update b256 "
         f"{floor['sac_update_b256_ms']:.2f} ms, action b1 {floor['sac_action_b1_ms']:.3f} ms); "
         "LeanRL reports 725, CleanRL 127"),
        ("sac-batched (32 copies, 16 gradient steps / batched step)", sps("sac-batched") + graphs("sac-batched"),
         f"eager update b256 {floor['sac_update_b256_ms']:.2f} ms"),
        ("ppo-stateless-pendulum (whole loop)", sps("ppo-stateless-pendulum") + graphs("ppo-stateless-pendulum"),
         "PureJaxRL-style: millions"),
        ("dqn-cartpole-fast", sps("dqn-cartpole-fast") + graphs("dqn-cartpole-fast"),
         f"same preset on the CPU: {sps('dqn-cartpole-fast@cpu')}" if "dqn-cartpole-fast@cpu" in runs else "-"),
    ]
    head = f"device: {figures['device']} ({figures['gpu'] or 'CPU'}), torch {figures['torch']}"
    lines = [head, "", "| work | relayrl | reference (same device) |", "|---|---|---|"]
    lines += [f"| {a} | {b} | {c} |" for a, b, c in rows]
    return "\n".join(lines)


# ---- smoke: train, evaluate, export, load -------------------------------------------------

def smoke_configs(steps: int) -> list[tuple[str, str, list[str]]]:
    """(label, preset, overrides): each algorithm at its smallest, `steps` env steps."""
    n = steps
    small = [f"train.total_steps={n}", f"eval.interval={n}", "eval.episodes=1", "train.checkpoint_interval=0",
             f"train.policy_save_interval={n}", f"train.log_interval={n}"]
    return [
        ("dqn", "dqn", [*small, f"train.initial_collect_steps={n // 3}", "agent.batch_size=16"]),
        ("sac", "sac-pendulum", [*small, f"train.initial_collect_steps={n // 3}", "agent.batch_size=16",
                                 "env.max_episode_steps=50"]),
        ("ppo", "ppo", [*small, "train.collect_steps=64", "agent.batch_size=32", "agent.n_epochs=1"]),
        ("bptt", "bptt-pendulum", [f"train.total_steps={max(n, 400)}", f"eval.interval={max(n, 400)}",
                                   "agent.batch_size=4", "agent.rollout_steps=20"]),
        ("pixel-ddqn", "dqn-pong-fast", [*small, f"train.initial_collect_steps={n // 3}", "agent.batch_size=8",
                                         "env.num_envs=2", "replay.size=2000", "env.max_episode_steps=50"]),
        ("pixel-ppo", "ppo-pong", [*small, "env.num_envs=2", "train.collect_steps=64", "agent.batch_size=32",
                                   "env.max_episode_steps=50"]),
    ]


def smoke(device: torch.device, steps: int) -> bool:
    """Train each algorithm for `steps` env steps on `device`, then evaluate, export and load its
    policy; one PASS/FAIL line each (SKIP for the pixel runs without ale-py). True when none failed."""
    import relayrl
    from relayrl.presets import load_config

    ok = True
    for label, preset, overrides in smoke_configs(steps):
        t0 = time.perf_counter()
        if label.startswith("pixel-") and importlib.util.find_spec("ale_py") is None:
            print(f"SKIP {label}: ale-py is not installed (pip install 'relayrl[atari]')", flush=True)
            continue
        try:
            config = load_config(preset, overrides)
            config.device = str(device)
            with tempfile.TemporaryDirectory() as tmp:
                run = Path(tmp) / "run"
                relayrl.train(config, run, progress=False)
                returns = relayrl.evaluate(run, episodes=1)
                exported = relayrl.export_policy(run)
                policy = relayrl.load_policy(run, device=str(device))
                program = torch.export.load(str(exported))
                obs = torch.zeros(2, *policy.obs_shape, dtype=policy.obs_dtype)
                action = policy(obs)
                exported_action = program.module()(obs)
                if len(action) != 2 or exported_action.shape[0] != 2:
                    raise RuntimeError(f"a batch of 2 observations gave {len(action)} and "
                                       f"{exported_action.shape[0]} actions")
            print(f"PASS {label}: {preset} on {device}, {config.train.total_steps} env steps, "
                  f"eval return {returns.mean:.1f}, "
                  f"exported and loaded ({time.perf_counter() - t0:.1f} s)", flush=True)
        except Exception as e:  # every algorithm gets its line, whatever the one before did
            ok = False
            print(f"FAIL {label}: {preset} on {device}: {type(e).__name__}: {e}", flush=True)
            traceback.print_exc(file=sys.stderr)
    return ok


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--device", default="cuda", help="cuda (default), cuda:N or cpu")
    p.add_argument("--seconds", type=float, default=30.0, help="steady seconds per run at most (default 30)")
    p.add_argument("--max-steps", type=int, default=0,
                   help="env steps per run at most, below each run's own cap (0: none; for a quick CPU check)")
    p.add_argument("--out", default=None, help="JSON file (default: $OUT/gpu.json when OUT is set, else gpu.json)")
    p.add_argument("--smoke", action="store_true", help="train, evaluate, export and load each algorithm instead")
    p.add_argument("--steps", type=int, default=300, help="--smoke: env steps per algorithm (default 300)")
    p.add_argument("--profile", choices=[r[0] for r in RUNS], default=None,
                   help="profile one run (cProfile, 40 functions by own time) instead")
    p.add_argument("--syncs", nargs="+", choices=[r[0] for r in RUNS], default=None,
                   help="count the host syncs of these runs by the lines causing them (CUDA) instead")
    p.add_argument("--only", nargs="+", choices=[r[0] for r in RUNS], default=None,
                   help="time these runs alone (no floors, no variants) and print their JSON")
    args = p.parse_args(argv)
    device = check_device(args.device)
    if args.seconds <= 0 or args.steps < 30 or args.max_steps < 0:
        fail(f"--seconds must be > 0, --steps >= 30 and --max-steps >= 0 (got {args.seconds}, {args.steps}, "
             f"{args.max_steps})")
    if args.smoke:
        return 0 if smoke(device, args.steps) else 1
    out = Path(args.out) if args.out else Path(os.environ["OUT"]) / "gpu.json" if os.environ.get("OUT") \
        else Path("gpu.json")
    if args.syncs:
        syncs(args.syncs, device, args.seconds, out.with_name("syncs.txt"))
        return 0
    if args.profile:
        profile(args.profile, device, args.seconds, out.with_name(f"profile-{args.profile}.txt"))
        return 0
    figures = bench(device, args.seconds, out, args.max_steps, args.only)
    print(json.dumps(figures["runs"]) if args.only else table(figures))
    print(f"figures: {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
