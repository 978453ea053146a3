"""DQN on CartPole: relayrl against Stable-Baselines3 in the same run, as wall-clock ratios.

    python bench/dqn_cartpole.py --peer-python bench/.venv-peers/bin/python [--settings tutorial zoo]
        [--seeds 0 1 2] [--threads N]

Each (setting, seed) runs relayrl and SB3 one after the other in fresh processes, so both
see the same machine load; the table reports learn() wall-clock (evaluations included,
process start-up excluded), evaluation time, final greedy return and relayrl/SB3.
Peers live only in the bench venv: `bash bench/setup_peers.sh`. With `--tfagents-python`
(a venv from `bash bench/setup_tfagents.sh`), the tutorial setting also runs TF-Agents' own
tutorial code (bench/tfagents_dqn_tutorial.py) for each seed, after SB3: its wall-clock is its
training loop plus evaluations, as for the other two. SB3 runs on torch's default threads
(every core); relayrl on its preset's one, or `--threads N` (0: torch's default, as SB3).

Settings:
  tutorial  TF-Agents' DQN tutorial: CartPole-v0, (100, 50), Adam 1e-3, batch 64, squared
            loss, no clipping, 100 random steps, 1 collect + 1 gradient step per iteration,
            20,000 iterations, eval every 1,000 steps over 10 episodes, epsilon 0.1.
  zoo       RL-Zoo's CartPole-v1 DQN: lr 2.3e-3, batch 64, buffer 100k, learning_starts 1000,
            gamma 0.99, target update every 10 env steps, train_freq 256, gradient_steps 128,
            exploration 1.0 -> 0.04 over 16% of 50,000 steps, (256, 256), eval every 5,000.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

from _workers import report, run_worker, sb3_eval_callback  # bench/ is on sys.path when a script runs

# relayrl --set overrides that express each setting on top of the dqn-cartpole preset.
RELAYRL = {
    "tutorial": [],
    "zoo": [
        "env.id=CartPole-v1", "env.time_limit_terminates=false", "train.total_steps=50000",
        "train.initial_collect_steps=1000",
        "train.collect_steps=256", "train.gradient_steps=128", "eval.interval=5000",
        "agent.hidden=[256,256]", "agent.init='torch'", "agent.lr=2.3e-3", "agent.adam_eps=1e-8",
        "agent.gamma=0.99", "agent.loss='huber'", "agent.grad_clip=10.0",
        # SB3 copies the target every 10 env steps, i.e. between bursts of 128 gradient steps.
        "agent.target_update_period=128", "agent.tau=1.0",
        "agent.epsilon_start=1.0", "agent.epsilon_end=0.04", "agent.epsilon_decay_steps=8000",
        "train.checkpoint_interval=0", "train.policy_save_interval=0",
    ],
}


def run_relayrl(setting: str, seed: int, threads: int) -> dict:
    import tempfile

    import relayrl
    import relayrl.dispatch  # the run's modules (and torch) load before the timer, as process start-up
    import relayrl.training.local  # noqa: F401

    threads_set = [f"train.torch_threads={threads}"] if threads >= 0 else []
    config = relayrl.load_config("dqn-cartpole", RELAYRL[setting] + threads_set, seed=seed)
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        result = relayrl.train(config, os.path.join(d, "run"), progress=False)
        wall = time.perf_counter() - t0
        rows = relayrl.training.run_dir.RunDir(result.run_dir).read_metrics()
    eval_s = sum(r.get("eval_s", 0.0) for r in rows)
    return {"wall_s": wall, "eval_s": eval_s, "final": result.final["average_return"],
            "curve": [(r["step"], r["average_return"]) for r in rows]}


def run_sb3(setting: str, seed: int) -> dict:
    import gymnasium as gym
    import torch
    from stable_baselines3 import DQN

    if setting == "tutorial":
        env_id, total, eval_every = "CartPole-v0", 20_100, 1_000
        kwargs = dict(learning_rate=1e-3, batch_size=64, buffer_size=100_000, learning_starts=100,
                      gamma=1.0, target_update_interval=1, train_freq=1, gradient_steps=1,
                      exploration_fraction=1e-9, exploration_initial_eps=0.1, exploration_final_eps=0.1,
                      max_grad_norm=1e9, policy_kwargs=dict(net_arch=[100, 50],
                      optimizer_kwargs=dict(eps=1e-7)))
    else:
        env_id, total, eval_every = "CartPole-v1", 50_000, 5_000
        kwargs = dict(learning_rate=2.3e-3, batch_size=64, buffer_size=100_000, learning_starts=1000,
                      gamma=0.99, target_update_interval=10, train_freq=256, gradient_steps=128,
                      exploration_fraction=0.16, exploration_final_eps=0.04,
                      policy_kwargs=dict(net_arch=[256, 256]))
    model = DQN("MlpPolicy", gym.make(env_id), seed=seed, verbose=0, **kwargs)
    if setting == "tutorial":
        # TF-Agents' tutorial uses the element-wise squared loss: SB3 hard-codes Huber, so swap it.
        import stable_baselines3.dqn.dqn as sb3_dqn

        sb3_dqn.F.smooth_l1_loss = torch.nn.functional.mse_loss  # mean (x - y)^2, no 1/2
    cb = sb3_eval_callback(env_id, eval_every, 10, seed)
    t0 = time.perf_counter()
    model.learn(total_timesteps=total, callback=cb)
    wall = time.perf_counter() - t0
    return {"wall_s": wall, "eval_s": cb.eval_s, "final": cb.curve[-1][1] if cb.curve else float("nan"),
            "curve": cb.curve}


def worker(argv: list[str]) -> None:
    which, setting, seed = argv[0], argv[1], int(argv[2])
    threads = int(argv[3]) if len(argv) > 3 else -1  # bench/ab.py passes none: the preset's
    out = run_relayrl(setting, seed, threads) if which == "relayrl" else run_sb3(setting, seed)
    report(out)


def spawn(python: str, which: str, setting: str, seed: int, threads: int = -1) -> dict:
    result, proc = run_worker(python, __file__, [which, setting, str(seed), str(threads)])
    if result is not None:
        return result
    raise RuntimeError(f"{which} worker failed:\n{proc.stderr[-3000:]}")


def run_tfagents(python: str, seed: int) -> dict:
    """TF-Agents' tutorial (bench/tfagents_dqn_tutorial.py) in its own venv, one thread."""
    import subprocess
    import tempfile

    script = os.path.join(os.path.dirname(os.path.abspath(__file__)), "tfagents_dqn_tutorial.py")
    with tempfile.TemporaryDirectory() as d:
        out = os.path.join(d, "tfa.json")
        proc = subprocess.run([python, script, "--seed", str(seed), "--json", out], capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"TF-Agents tutorial failed:\n{proc.stderr[-3000:]}")
        with open(out) as f:
            r = json.load(f)
    return {"wall_s": r["train_seconds"] + r["eval_seconds"], "eval_s": r["eval_seconds"],
            "final": r["evals"][-1][1], "curve": r["evals"]}


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        worker(sys.argv[2:])
        return
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--peer-python", default="bench/.venv-peers/bin/python")
    p.add_argument("--settings", nargs="+", default=["tutorial", "zoo"], choices=sorted(RELAYRL))
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--tfagents-python", help="a TF-Agents venv's python: adds TF-Agents to the tutorial setting")
    p.add_argument("--threads", type=int, default=-1,
                   help="relayrl's train.torch_threads (0: torch's default, as SB3; default: the preset's)")
    p.add_argument("--json", help="also write every result here")
    args = p.parse_args()
    rows, results = [], {}
    print("| setting | seed | relayrl s (eval s) | SB3 s (eval s) | relayrl / SB3 | final return relayrl | SB3 |")
    print("|---|---|---|---|---|---|---|")
    for setting in args.settings:
        ratios = []
        for seed in args.seeds:
            ours = spawn(sys.executable, "relayrl", setting, seed, args.threads)
            peer = spawn(args.peer_python, "sb3", setting, seed)
            ratio = ours["wall_s"] / peer["wall_s"]
            ratios.append(ratio)
            results[f"{setting}/{seed}"] = {"relayrl": ours, "sb3": peer, "relayrl_threads": args.threads}
            print(f"| {setting} | {seed} | {ours['wall_s']:.1f} ({ours['eval_s']:.1f}) | "
                  f"{peer['wall_s']:.1f} ({peer['eval_s']:.1f}) | {ratio:.2f} | {ours['final']:.1f} | "
                  f"{peer['final']:.1f} |", flush=True)
            if setting == "tutorial" and args.tfagents_python:
                tfa = run_tfagents(args.tfagents_python, seed)
                results[f"{setting}/{seed}"]["tf_agents"] = tfa
                print(f"|   TF-Agents | {seed} | relayrl / TF-Agents {ours['wall_s'] / tfa['wall_s']:.2f} | "
                      f"TF-Agents {tfa['wall_s']:.1f} s ({tfa['eval_s']:.1f}) | final {tfa['final']:.1f} |", flush=True)
        rows.append((setting, statistics.mean(ratios)))
    for setting, r in rows:
        print(f"mean relayrl/SB3 wall-clock, {setting}: {r:.2f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
