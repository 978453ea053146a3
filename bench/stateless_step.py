"""Stateless Pendulum: raw stepping throughput against Gymnasium, and BPTT training speed.

    .venv/bin/python bench/stateless_step.py [--device cpu] [--batches 1,32,4096,65536]
        [--seconds 1.0] [--torchrl-python bench/.venv-peers/bin/python] [--learn]
        [--torchrl-learn SEED [SEED ...]] [--json bench/results/stateless.json]

Stepping (issue 6). Env steps/s = batch size x batched steps/s, random actions, no autograd
(`torch.inference_mode`), one thread (`torch.set_num_threads(1)`; 2 with `--threads 2`):

  stateless  `make_pendulum()` (observation [cos th, sin th, thdot], as Gymnasium's), the state
             threaded by hand: `out = env.step(state, action); state = out.state`
  adapter    `StatelessBatchEnv(make_pendulum(), B)`: the batched env the train loop sees,
             with auto-reset of finished rows and the true final observation kept
  gymnasium  `gymnasium.vector.SyncVectorEnv` of B `Pendulum-v1` (up to `--gym-max`, 4,096 by
             default: 65,536 Python envs take minutes to build and step), the peer we compare to

Actions are drawn before timing (a pool of 16 batches, cycled) so the timed loop is the env
alone; each figure is the median of 3 timed repeats of `--seconds` after one warm-up step,
and the three envs run one after another at each size, so they see the same load on this
shared machine. On CUDA the clock stops after a synchronize. `ratio` = stateless / gymnasium.

BPTT (the TorchRL Pendulum tutorial's training: batch 32, 100-step rollouts, Adam, clipping):
iterations/s of `train_bptt` (fast and, slower, generic autograd through `rollout`), each over
`--bptt-iterations` iterations in this process, and of the tutorial's own TorchRL code (env,
transforms and loop as the tutorial writes them, TorchRL 0.14 spec names) in a fresh process
of `--torchrl-python`, when that interpreter has torchrl. `--learn` also runs the full
625-iteration training for seeds 0, 1, 2 and prints the final-50-iteration means.

`--torchrl-learn 0 1 2` runs, instead of all the above, the tutorial's own full training (625
iterations, seeded as the tutorial seeds it: `torch.manual_seed(seed)`, `env.set_seed(seed)`)
in a fresh `--torchrl-python` process per seed, and prints per seed the final-50-iteration means
of the tutorial's two logged figures (mean reward over the rollout, mean last-step reward), its
iterations/s (one thread) and the process's wall time: the reference for `--learn`'s figures.
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

from _workers import report, run_worker  # bench/ is on sys.path when a script runs

# the peers' venv (bash bench/setup_peers.sh installs torchrl there)
DEFAULT_TORCHRL = os.path.join(os.path.dirname(os.path.abspath(__file__)), ".venv-peers", "bin", "python")


def timed(step: Callable[[], int], seconds: float, sync: Callable[[], None]) -> float:
    """Median units/s of 3 repeats; step() does some work and returns how many units."""
    step()
    sync()
    rates = []
    for _ in range(3):
        units, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            units += step()
        sync()
        rates.append(units / (time.perf_counter() - t0))
    return statistics.median(rates)


def bench_stateless(batch: int, device: str, seconds: float, adapter: bool) -> float:
    import torch

    from relayrl.envs.stateless import make_generator, make_pendulum
    from relayrl.envs.stateless.adapter import StatelessBatchEnv

    env = make_pendulum(device=device)
    gen = make_generator(0)
    pool = [env.rand_action((batch,), gen, device) for _ in range(16)]
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    i = 0
    with torch.inference_mode():
        if adapter:
            benv = StatelessBatchEnv(env, batch, device, seed=0)
            benv.reset()

            def step() -> int:
                nonlocal i
                for _ in range(10):
                    benv.step(pool[i % 16])
                    i += 1
                return 10 * batch
        else:
            state, _ = env.reset((batch,), gen, device)

            def step() -> int:
                nonlocal i, state
                for _ in range(10):
                    state = env.step(state, pool[i % 16]).state
                    i += 1
                return 10 * batch

        return timed(step, seconds, sync)


def bench_gymnasium(batch: int, seconds: float) -> float:
    import gymnasium as gym
    import numpy as np

    envs = gym.vector.SyncVectorEnv([lambda: gym.make("Pendulum-v1") for _ in range(batch)])
    envs.reset(seed=0)
    rng = np.random.default_rng(0)
    pool = [rng.uniform(-2, 2, size=(batch, 1)).astype(np.float32) for _ in range(16)]
    i = 0

    def step() -> int:
        nonlocal i
        envs.step(pool[i % 16])
        i += 1
        return batch

    rate = timed(step, seconds, lambda: None)
    envs.close()
    return rate


def bench_bptt(iterations: int, fast: bool, device: str, threads: int) -> float:
    from relayrl.agents.bptt.bptt import train_bptt
    from relayrl.agents.bptt.config import BpttConfig

    c = BpttConfig(fast=fast)
    train_bptt(c, iterations=3, device=device, torch_threads=threads)  # warm-up
    return train_bptt(c, iterations=iterations, device=device, torch_threads=threads).iterations_per_s


def tutorial_trainer(seed: int) -> Callable[[], tuple[float, float]]:
    """The TorchRL Pendulum tutorial's env, transforms, policy and optimiser (TorchRL 0.14 names),
    seeded as the tutorial seeds them; returns one training iteration, which gives the
    tutorial's two logged figures: mean reward over the rollout and mean last-step reward."""
    import torch
    from tensordict import TensorDict, TensorDictBase
    from tensordict.nn import TensorDictModule
    from torch import nn
    from torchrl.data import Bounded, Composite, Unbounded
    from torchrl.envs import CatTensors, EnvBase, Transform, TransformedEnv, UnsqueezeTransform
    from torchrl.envs.transforms.transforms import _apply_to_composite

    torch.set_num_threads(1)

    def angle_normalize(x):
        return ((x + torch.pi) % (2 * torch.pi)) - torch.pi

    def make_params(g=10.0, batch_size=None):
        td = TensorDict({"params": TensorDict({"max_speed": 8, "max_torque": 2.0, "dt": 0.05, "g": g,
                                               "m": 1.0, "l": 1.0}, [])}, [])
        return td.expand(batch_size).contiguous() if batch_size else td

    def composite_from_td(td):
        return Composite({k: composite_from_td(v) if isinstance(v, TensorDictBase)
                          else Unbounded(dtype=v.dtype, device=v.device, shape=v.shape) for k, v in td.items()},
                         shape=td.shape)

    class PendulumEnv(EnvBase):
        batch_locked = False

        def __init__(self, seed=0):
            super().__init__(device="cpu", batch_size=[])
            p = make_params()
            self.observation_spec = Composite(
                th=Bounded(low=-torch.pi, high=torch.pi, shape=(), dtype=torch.float32),
                thdot=Bounded(low=-p["params", "max_speed"], high=p["params", "max_speed"], shape=(),
                              dtype=torch.float32),
                params=composite_from_td(p["params"]), shape=())
            self.state_spec = self.observation_spec.clone()
            self.action_spec = Bounded(low=-p["params", "max_torque"], high=p["params", "max_torque"], shape=(1,),
                                       dtype=torch.float32)
            self.reward_spec = Unbounded(shape=(*p.shape, 1))
            self.set_seed(seed)

        gen_params = staticmethod(make_params)

        def _set_seed(self, seed):
            self.rng = torch.manual_seed(seed)

        def _reset(self, td):
            if td is None or td.is_empty():
                td = self.gen_params(batch_size=self.batch_size)
            th = torch.rand(td.shape, generator=self.rng) * 2 * torch.pi - torch.pi
            thdot = torch.rand(td.shape, generator=self.rng) * 2 - 1
            return TensorDict({"th": th, "thdot": thdot, "params": td["params"]}, batch_size=td.shape)

        @staticmethod
        def _step(td):
            th, thdot, p = td["th"], td["thdot"], td["params"]
            u = td["action"].squeeze(-1).clamp(-p["max_torque"], p["max_torque"])
            costs = angle_normalize(th) ** 2 + 0.1 * thdot**2 + 0.001 * u**2
            new_thdot = thdot + (3 * p["g"] / (2 * p["l"]) * th.sin() + 3.0 / (p["m"] * p["l"] ** 2) * u) * p["dt"]
            new_thdot = new_thdot.clamp(-p["max_speed"], p["max_speed"])
            reward = -costs.view(*td.shape, 1)
            return TensorDict({"th": th + new_thdot * p["dt"], "thdot": new_thdot, "params": p, "reward": reward,
                               "done": torch.zeros_like(reward, dtype=torch.bool)}, td.shape)

    class SinCos(Transform):
        def __init__(self, fn, in_keys, out_keys):
            super().__init__(in_keys=in_keys, out_keys=out_keys)
            self.fn = fn

        def _apply_transform(self, x):
            return self.fn(x)

        def _reset(self, td, td_reset):
            return self._call(td_reset)

        @_apply_to_composite
        def transform_observation_spec(self, spec):
            return Bounded(low=-1, high=1, shape=spec.shape, dtype=spec.dtype, device=spec.device)

    env = TransformedEnv(PendulumEnv(), UnsqueezeTransform(dim=-1, in_keys=["th", "thdot"],
                                                           in_keys_inv=["th", "thdot"]))
    env.append_transform(SinCos(torch.sin, ["th"], ["sin"]))
    env.append_transform(SinCos(torch.cos, ["th"], ["cos"]))
    env.append_transform(CatTensors(in_keys=["sin", "cos", "thdot"], dim=-1, out_key="observation", del_keys=False))
    torch.manual_seed(seed)
    env.set_seed(seed)
    net = nn.Sequential(nn.LazyLinear(64), nn.Tanh(), nn.LazyLinear(64), nn.Tanh(), nn.LazyLinear(64), nn.Tanh(),
                        nn.LazyLinear(1))
    policy = TensorDictModule(net, in_keys=["observation"], out_keys=["action"])
    optim = torch.optim.Adam(policy.parameters(), lr=2e-3)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optim, 20_000)

    def iteration() -> tuple[float, float]:
        init_td = env.reset(env.gen_params(batch_size=[32]))
        rollout = env.rollout(100, policy, tensordict=init_td, auto_reset=False)
        traj_return = rollout["next", "reward"].mean()
        (-traj_return).backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        optim.step()
        optim.zero_grad()
        scheduler.step()
        return traj_return.item(), rollout[..., -1]["next", "reward"].mean().item()

    return iteration


def torchrl_tutorial(iterations: int) -> float:
    """Iterations/s of the tutorial's training over `iterations` iterations after 3 untimed ones."""
    iteration = tutorial_trainer(0)
    for _ in range(3):
        iteration()
    t0 = time.perf_counter()
    for _ in range(iterations):
        iteration()
    return iterations / (time.perf_counter() - t0)


def torchrl_tutorial_learn(seed: int, iterations: int = 20_000 // 32) -> dict:
    """The tutorial's full training (625 iterations) for one seed: final-50-iteration means of its
    two logged figures, and iterations/s over the whole run."""
    import tensordict
    import torch
    import torchrl

    iteration = tutorial_trainer(seed)
    t0 = time.perf_counter()
    logs = [iteration() for _ in range(iterations)]
    rate = iterations / (time.perf_counter() - t0)
    return {"seed": seed, "mean_reward_final50": statistics.mean(r for r, _ in logs[-50:]),
            "last_reward_final50": statistics.mean(last for _, last in logs[-50:]), "it_per_s": rate,
            "iterations": iterations, "torch": torch.__version__, "torchrl": torchrl.__version__,
            "tensordict": tensordict.__version__}


def torchrl_learn(python: str, seeds: list[int]) -> list[dict]:
    """`torchrl_tutorial_learn` for each seed, each in a fresh process of `python`; prints a table."""
    print(f"TorchRL tutorial training ({python}), 625 iterations, final-50 means:")
    print(f"{'seed':>6} {'mean reward':>12} {'last-step reward':>17} {'it/s':>7} {'wall s':>8}")
    out = []
    for seed in seeds:
        t0 = time.perf_counter()
        res, proc = run_worker(python, os.path.abspath(__file__), ["--torchrl-learn", str(seed)])
        wall = time.perf_counter() - t0
        if res is None:
            print(f"torchrl worker failed (seed {seed}):\n{proc.stderr[-2000:]}")
            continue
        out.append({**res, "wall_s": wall})
        print(f"{seed:>6} {res['mean_reward_final50']:>12.3f} {res['last_reward_final50']:>17.3f} "
              f"{res['it_per_s']:>7.2f} {wall:>8.1f}", flush=True)
    if out:
        print(f"{'mean':>6} {statistics.mean(o['mean_reward_final50'] for o in out):>12.3f} "
              f"{statistics.mean(o['last_reward_final50'] for o in out):>17.3f}   (targets >= -3.0, >= -0.7)")
    return out


def learn(device: str) -> list[dict]:
    from relayrl.agents.bptt.bptt import train_bptt

    out = []
    for seed in range(3):
        r = train_bptt(seed=seed, device=device)
        out.append({"seed": seed, "mean_reward_final50": statistics.mean(r.mean_reward[-50:]),
                    "last_reward_final50": statistics.mean(r.last_reward[-50:]), "it_per_s": r.iterations_per_s})
        print(f"  seed {seed}: mean reward {out[-1]['mean_reward_final50']:.3f}, last-step reward "
              f"{out[-1]['last_reward_final50']:.3f} (final 50 of 625), {r.iterations_per_s:.1f} it/s", flush=True)
    print(f"  seeds 0-2: mean reward {statistics.mean(o['mean_reward_final50'] for o in out):.3f}, last-step "
          f"reward {statistics.mean(o['last_reward_final50'] for o in out):.3f} (targets >= -3.0, >= -0.7)")
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--batches", default="1,32,4096,65536")
    p.add_argument("--gym-max", type=int, default=4096)
    p.add_argument("--seconds", type=float, default=1.0)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--bptt-iterations", type=int, default=100)
    p.add_argument("--torchrl-python", default=DEFAULT_TORCHRL)
    p.add_argument("--torchrl-iterations", type=int, default=20)
    p.add_argument("--learn", action="store_true")
    p.add_argument("--torchrl-learn", type=int, nargs="+", default=[], metavar="SEED")
    p.add_argument("--json", default="")
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    a = p.parse_args()
    if a.worker:
        report(torchrl_tutorial_learn(a.torchrl_learn[0]) if a.torchrl_learn
               else {"it_per_s": torchrl_tutorial(a.torchrl_iterations)})
        return

    import torch

    torch.set_num_threads(a.threads)
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "src"))
    cpu = platform.processor() or platform.machine()
    dev = torch.cuda.get_device_name() if a.device.startswith("cuda") else f"{cpu}, {os.cpu_count()} cores"
    print(f"# stateless Pendulum, {datetime.date.today()}, {dev}, torch {torch.__version__}, "
          f"threads {a.threads}, device {a.device}")
    if a.torchrl_learn:  # the TorchRL learning reference alone
        if not a.torchrl_python:
            sys.exit("--torchrl-learn needs --torchrl-python")
        learned = torchrl_learn(a.torchrl_python, a.torchrl_learn)
        if a.json:
            with open(a.json, "w") as f:
                json.dump({"date": str(datetime.date.today()), "machine": dev, "torchrl_python": a.torchrl_python,
                           "torchrl_learn": learned}, f, indent=1)
        return
    rows = []
    print(f"{'batch':>8} {'stateless steps/s':>18} {'adapter steps/s':>16} {'gymnasium steps/s':>18} {'ratio':>8}")
    for b in [int(x) for x in a.batches.split(",")]:
        ours = bench_stateless(b, a.device, a.seconds, adapter=False)
        adapted = bench_stateless(b, a.device, a.seconds, adapter=True)
        gym_rate = bench_gymnasium(b, a.seconds) if b <= a.gym_max else None
        ratio = ours / gym_rate if gym_rate else None
        rows.append({"batch": b, "stateless": ours, "adapter": adapted, "gymnasium": gym_rate, "ratio": ratio})
        gym_txt = f"{gym_rate:,.0f}" if gym_rate else "-"
        ratio_txt = "-" if ratio is None else f"{ratio:.2f}x" if ratio < 10 else f"{ratio:,.0f}x"
        print(f"{b:>8} {ours:>18,.0f} {adapted:>16,.0f} {gym_txt:>18} {ratio_txt:>8}", flush=True)
    bptt = {"fast": bench_bptt(a.bptt_iterations, True, a.device, a.threads),
            "generic": bench_bptt(max(10, a.bptt_iterations // 5), False, a.device, a.threads)}
    if a.torchrl_python and not os.path.exists(a.torchrl_python):
        print(f"no TorchRL row: {a.torchrl_python} does not exist (bash bench/setup_peers.sh makes the peers' venv)")
    elif a.torchrl_python:
        res, proc = run_worker(a.torchrl_python, os.path.abspath(__file__),
                               ["--torchrl-iterations", str(a.torchrl_iterations)])
        if res is None:
            print(f"torchrl worker failed:\n{proc.stderr[-2000:]}")
        bptt["torchrl_tutorial"] = res["it_per_s"] if res else None
    print("\nBPTT iterations/s (batch 32, 100-step rollouts):")
    for name, rate in bptt.items():
        vs = bptt.get("torchrl_tutorial")
        extra = f"  ({rate / vs:.1f}x TorchRL's tutorial)" if vs and rate and name != "torchrl_tutorial" else ""
        print(f"  {name:<17} {rate or float('nan'):7.1f}{extra}")
    learned = None
    if a.learn:
        print("\nLearning (625 iterations):")
        learned = learn(a.device)
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"date": str(datetime.date.today()), "machine": dev, "device": a.device, "threads": a.threads,
                       "torch": torch.__version__, "stepping": rows, "bptt_it_per_s": bptt, "learn": learned}, f,
                      indent=1)


if __name__ == "__main__":
    main()
