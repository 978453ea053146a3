"""PPO with RL Zoo's settings: relayrl against Stable-Baselines3 in the same run, as env steps/s.

    python bench/ppo.py [--peer-python bench/.venv-peers/bin/python] [--settings cartpole lunarlander]
        [--seeds 0 1] [--lunarlander-steps 196608] [--json FILE]

Each (setting, seed) runs relayrl, then SB3, each in a fresh process, so both see the same
machine load. Timed: the whole training call (relayrl.train / model.learn), evaluation
included, process start-up and imports excluded; the table gives env steps/s over it, the
evaluation seconds inside it, steps/s with evaluation taken out, the final greedy return and
the speed ratio relayrl / SB3 (> 1: relayrl faster). Both sides evaluate the deterministic
policy on the same schedule (10 episodes at the start, every `eval` env steps and at the end). relayrl
runs with one torch thread (`train.torch_threads = 1`, its default), SB3 with torch's default,
as in the other bench scripts. Peers live only in the bench venv: `bash bench/setup_peers.sh`.

Settings (RL Zoo's ppo.yml; the rest SB3's PPO defaults: separate 64-64 tanh MLPs, orthogonal
init, vf_coef 0.5, max grad norm 0.5, per-minibatch advantage normalisation):
  cartpole     the ppo-cartpole preset: CartPole-v1, 8 envs, n_steps 32, batch 256, 20 epochs,
               gamma 0.98, gae_lambda 0.8, lr and clip range linear from 1e-3 / 0.2 to 0,
               100,000 env steps, eval every 10,240.
  lunarlander  the ppo-lunarlander preset's settings: LunarLander-v3, 16 envs, n_steps 1024,
               batch 64, 4 epochs, gamma 0.999, gae_lambda 0.98, ent_coef 0.01, lr 3e-4, clip
               0.2, eval every 98,304; 196,608 env steps (12 rollouts) by default instead of
               the preset's 1M: the speed ratio, not the learning, is measured.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time

from _workers import report, run_worker, sb3_eval_callback  # bench/ is on sys.path when a script runs

EVAL_EPISODES = 10
NO_FILES = ["train.checkpoint_interval=0", "train.policy_save_interval=0"]
# Per setting: the Gymnasium id, env copies, eval interval, default env steps, the relayrl --set
# overrides on top of the ppo-cartpole preset and the SB3 PPO arguments.
SETTINGS: dict[str, dict] = {
    "cartpole": {"env": "CartPole-v1", "n_envs": 8, "eval": 10_240, "steps": 100_000, "overrides": [],
                 "sb3": dict(n_steps=32, batch_size=256, n_epochs=20, gamma=0.98, gae_lambda=0.8, ent_coef=0.0,
                             linear=(1e-3, 0.2))},
    "lunarlander": {"env": "LunarLander-v3", "n_envs": 16, "eval": 98_304, "steps": 196_608,
                    "overrides": ["env.id='LunarLander-v3'", "env.num_envs=16", "train.collect_steps=16384",
                                  "train.log_interval=16384", "agent.lr=3e-4", "agent.lr_end=-1.0",
                                  "agent.clip_range=0.2", "agent.clip_range_end=-1.0", "agent.n_epochs=4",
                                  "agent.batch_size=64", "agent.gamma=0.999", "agent.gae_lambda=0.98",
                                  "agent.ent_coef=0.01"],
                    "sb3": dict(n_steps=1024, batch_size=64, n_epochs=4, gamma=0.999, gae_lambda=0.98, ent_coef=0.01,
                                linear=None)},
}


def relayrl_overrides(setting: str, steps: int) -> list[str]:
    """The setting as --set overrides on top of the ppo-cartpole preset."""
    s = SETTINGS[setting]
    return [*s["overrides"], f"train.total_steps={steps}", f"eval.interval={s['eval']}",
            f"eval.episodes={EVAL_EPISODES}", *NO_FILES]


def run_relayrl(setting: str, seed: int, steps: int) -> dict:
    import relayrl
    import relayrl.dispatch  # the run's modules (and torch) load before the timer, as process start-up
    import relayrl.training.local  # noqa: F401
    from relayrl.training.run_dir import RunDir

    config = relayrl.load_config("ppo-cartpole", relayrl_overrides(setting, steps), seed=seed)
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        result = relayrl.train(config, os.path.join(d, "run"), progress=False)
        wall = time.perf_counter() - t0
        rows = RunDir(result.run_dir).read_metrics()
    return {"steps": steps, "wall_s": wall, "eval_s": sum(r.get("eval_s", 0.0) for r in rows),
            "final": result.final["average_return"], "curve": [(r["step"], r["average_return"]) for r in rows]}


def run_sb3(setting: str, seed: int, steps: int, threads: int) -> dict:
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env

    if threads > 0:
        torch.set_num_threads(threads)
    s = SETTINGS[setting]
    kwargs = dict(s["sb3"])
    linear = kwargs.pop("linear")
    if linear is not None:  # RL Zoo's lin_<x>: x times the remaining fraction of training
        lr, clip = linear
        kwargs.update(learning_rate=lambda p: p * lr, clip_range=lambda p: p * clip)
    env = make_vec_env(s["env"], n_envs=s["n_envs"], seed=seed)  # RL Zoo's DummyVecEnv of Monitor-wrapped envs
    model = PPO("MlpPolicy", env, seed=seed, verbose=0, **kwargs)
    cb = sb3_eval_callback(s["env"], s["eval"], EVAL_EPISODES, seed, at_start=True)
    t0 = time.perf_counter()
    model.learn(total_timesteps=steps, callback=cb)
    if not cb.curve or cb.curve[-1][0] != model.num_timesteps:
        cb.evaluate()  # relayrl always evaluates at the end
    wall = time.perf_counter() - t0
    return {"steps": int(model.num_timesteps), "wall_s": wall, "eval_s": cb.eval_s, "final": cb.curve[-1][1],
            "curve": cb.curve}


def spawn(python: str, which: str, setting: str, seed: int, steps: int, threads: int = 0) -> dict:
    result, proc = run_worker(python, __file__, [which, setting, str(seed), str(steps), str(threads)])
    if result is None:
        raise RuntimeError(f"{which} worker failed:\n{proc.stderr[-3000:]}")
    return result


def rates(r: dict) -> tuple[float, float]:
    """Env steps/s over the whole training call, and with its evaluation time taken out."""
    return r["steps"] / r["wall_s"], r["steps"] / (r["wall_s"] - r["eval_s"])


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        which, setting, seed, steps, threads = sys.argv[2], sys.argv[3], *map(int, sys.argv[4:7])
        report(run_relayrl(setting, seed, steps) if which == "relayrl" else run_sb3(setting, seed, steps, threads))
        return
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--peer-python", default="bench/.venv-peers/bin/python")
    p.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    p.add_argument("--cartpole-steps", type=int, default=SETTINGS["cartpole"]["steps"])
    p.add_argument("--lunarlander-steps", type=int, default=SETTINGS["lunarlander"]["steps"])
    p.add_argument("--sb3-threads", type=int, default=0, help="SB3's torch threads; 0: torch's default")
    p.add_argument("--json", help="also write every result here")
    args = p.parse_args()
    results: dict[str, dict] = {}
    print("| setting | seed | relayrl steps/s (eval s) | SB3 steps/s (eval s) | relayrl / SB3 | "
          "without eval: relayrl / SB3 steps/s | ratio | final relayrl | SB3 |")
    print("|---|---|---|---|---|---|---|---|---|")
    summary = []
    for setting in args.settings:
        steps = getattr(args, f"{setting}_steps")
        whole, bare = [], []
        for seed in args.seeds:
            ours = spawn(sys.executable, "relayrl", setting, seed, steps)
            peer = spawn(args.peer_python, "sb3", setting, seed, steps, args.sb3_threads)
            (ow, ob), (pw, pb) = rates(ours), rates(peer)
            whole.append(ow / pw)
            bare.append(ob / pb)
            results[f"{setting}/{seed}"] = {"relayrl": ours, "sb3": peer}
            print(f"| {setting} | {seed} | {ow:,.0f} ({ours['eval_s']:.1f}) | {pw:,.0f} ({peer['eval_s']:.1f}) | "
                  f"{whole[-1]:.2f}x | {ob:,.0f} / {pb:,.0f} | {bare[-1]:.2f}x | {ours['final']:.1f} | "
                  f"{peer['final']:.1f} |", flush=True)
        summary.append(f"{setting}: relayrl / SB3 env steps/s, median over seeds {statistics.median(whole):.2f}x "
                       f"(without evaluation {statistics.median(bare):.2f}x)")
    print("\n".join(summary))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
