"""Minitaur env steps/s: pybullet's env alone, our Gymnasium adapter, gym.make, and make_env.

    .venv/bin/python bench/minitaur_env.py [--steps 2000]

Each row steps one env (render=False, pybullet DIRECT mode) with the same seeded uniform random
actions in [-1, 1], seeded once at the first reset, and resets it when an episode ends (fall or
1000 steps). Resets are inside the timing (a collector pays for them: each one rebuilds the
simulation) and also reported on their own, except for make_env, which resets inside its step.
Rows after the first show what each layer above pybullet costs.
Needs the extra: pip install 'relayrl[bullet]'.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from collections.abc import Callable
from importlib.metadata import version

import gymnasium as gym
import numpy as np
import torch

from relayrl.envs import make_env
from relayrl.envs.minitaur import ENV_ID, MinitaurEnv

Reset = Callable[[int | None], None]  # called with seed 0 first, then None
Step = Callable[[int], bool]  # takes an action index, says whether the episode ended


def bench(reset: Reset, step: Step, n: int) -> dict:
    reset(0)
    resets, reset_s = 0, 0.0
    start, cpu_start = time.perf_counter(), time.process_time()
    for i in range(n):
        if step(i):
            t = time.perf_counter()
            reset(None)
            reset_s += time.perf_counter() - t
            resets += 1
    seconds, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    return {
        "steps/s": n / seconds,
        "steps/CPU-s": n / cpu,
        "seconds": seconds,
        "episodes ended": resets,
        "ms/reset": 1000 * reset_s / resets if resets else float("nan"),
    }


def gym_rows(actions: np.ndarray) -> dict[str, dict]:
    rows = {}
    adapter = MinitaurEnv()
    inner = adapter._env  # pybullet's MinitaurBulletEnv itself: old API, so we count the 1000 steps
    count = [0]

    def inner_reset(seed: int | None) -> None:
        adapter.reset(seed=seed)  # seeds the randomizer the inner env draws from, then inner.reset()
        count[0] = 0

    def inner_step(i: int) -> bool:
        count[0] += 1
        return bool(inner.step(actions[i])[2]) or count[0] == 1000

    rows["pybullet MinitaurBulletEnv"] = bench(inner_reset, inner_step, len(actions))
    adapter.close()
    for name in ["relayrl MinitaurEnv", "gym.make (TimeLimit)"]:
        # gym.make as make_env builds it: TimeLimit + OrderEnforcing, no env checker.
        env = MinitaurEnv() if name.startswith("relayrl") else gym.make(ENV_ID, disable_env_checker=True)
        count[0] = 0

        def reset(seed: int | None, env: gym.Env = env) -> None:
            env.reset(seed=seed)
            count[0] = 0

        def step(i: int, env: gym.Env = env) -> bool:
            count[0] += 1
            _, _, terminated, truncated, _ = env.step(actions[i])
            return terminated or truncated or count[0] == 1000  # the bare adapter has no TimeLimit

        rows[name] = bench(reset, step, len(actions))
        env.close()
    return rows


def make_env_row(actions: np.ndarray) -> dict:
    batched = make_env(ENV_ID, 1)
    torch_actions = torch.from_numpy(actions).unsqueeze(1)

    def reset(seed: int | None) -> None:
        if seed is not None:  # later resets happen inside step
            batched.reset(seed=seed)

    def step(i: int) -> bool:
        out = batched.step(torch_actions[i])
        return bool(out.terminated.any() or out.truncated.any())

    row = bench(reset, step, len(actions))
    row["ms/reset"] = float("nan")
    batched.close()
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000)
    args = parser.parse_args()
    torch.set_num_threads(1)
    actions = np.random.default_rng(0).uniform(-1, 1, (args.steps, 8)).astype(np.float32)
    rows = gym_rows(actions)
    rows["make_env(num_envs=1)"] = make_env_row(actions)

    print(
        f"Minitaur, {args.steps} random steps per row, render=False; pybullet {version('pybullet')}, "
        f"{os.cpu_count()} CPUs ({platform.machine()}), load average {os.getloadavg()[0]:.1f}"
    )
    # steps/CPU-s: steps per second of this process's CPU time. pybullet DIRECT simulates in this
    # thread, so on a busy shared machine it is closer than steps/s to what an idle one does.
    columns = list(next(iter(rows.values())))
    print(f"{'row':<28}" + "".join(f"{c:>15}" for c in columns))
    for name, row in rows.items():
        print(f"{name:<28}" + "".join(f"{row[c]:>15.2f}" if c == "seconds" else f"{row[c]:>15.0f}" for c in columns))


if __name__ == "__main__":
    main()
