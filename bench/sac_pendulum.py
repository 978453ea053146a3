"""SAC on Pendulum-v1 with SB3's defaults: relayrl against Stable-Baselines3 in the same run.

    python bench/sac_pendulum.py [--peer-python bench/.venv-peers/bin/python] [--seeds 0 1 2]
        [--steps 20000] [--threads N] [--json FILE]

Both sides: batch 256, (256, 256) actor and critics, Adam 3e-4, 1 gradient step per env
step, 100 random steps first, buffer 1M, tau 0.005, automatic entropy tuning; greedy
evaluation over 10 episodes every 2,000 env steps. Each seed runs relayrl then SB3, each in
a fresh process, so both see the same machine load. The table reports env steps/s over the
whole learn() (evaluation included) and the final evaluation return. SB3 runs on torch's default
threads; relayrl on the sac-pendulum preset's one, or `--threads N` (0: torch's default, as SB3).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time

from _workers import report, run_worker, sb3_eval_callback

EVAL_EVERY, EVAL_EPISODES = 2_000, 10


def run_relayrl(seed: int, steps: int, threads: int) -> dict:
    import os

    import relayrl
    import relayrl.dispatch  # the run's modules (and torch) load before the timer, as process start-up
    import relayrl.training.local  # noqa: F401
    from relayrl.training.run_dir import RunDir

    overrides = [f"train.total_steps={steps}", f"eval.interval={EVAL_EVERY}", f"eval.episodes={EVAL_EPISODES}",
                 "train.checkpoint_interval=0", "train.policy_save_interval=0"]
    if threads >= 0:
        overrides.append(f"train.torch_threads={threads}")
    config = relayrl.load_config("sac-pendulum", overrides, seed=seed)
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        result = relayrl.train(config, os.path.join(d, "run"), progress=False)
        wall = time.perf_counter() - t0
        rows = RunDir(result.run_dir).read_metrics()
    return {"wall_s": wall, "eval_s": sum(r.get("eval_s", 0.0) for r in rows),
            "final": result.final["average_return"], "curve": [(r["step"], r["average_return"]) for r in rows]}


def run_sb3(seed: int, steps: int) -> dict:
    import gymnasium as gym
    from stable_baselines3 import SAC

    model = SAC("MlpPolicy", gym.make("Pendulum-v1"), seed=seed, verbose=0)
    cb = sb3_eval_callback("Pendulum-v1", EVAL_EVERY, EVAL_EPISODES, seed)
    t0 = time.perf_counter()
    model.learn(total_timesteps=steps, callback=cb)
    if not cb.curve or cb.curve[-1][0] != steps:
        cb.evaluate()  # relayrl always evaluates at the end
    wall = time.perf_counter() - t0
    return {"wall_s": wall, "eval_s": cb.eval_s, "final": cb.curve[-1][1], "curve": cb.curve}


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        which, seed, steps, threads = sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
        report(run_relayrl(seed, steps, threads) if which == "relayrl" else run_sb3(seed, steps))
        return
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--peer-python", default="bench/.venv-peers/bin/python")
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--steps", type=int, default=20_000)
    p.add_argument("--threads", type=int, default=-1,
                   help="relayrl's train.torch_threads (0: torch's default, as SB3; default: the preset's)")
    p.add_argument("--json", help="also write every result here")
    args = p.parse_args()
    results, ratios = {}, []
    print("| seed | relayrl steps/s (eval s) | SB3 steps/s (eval s) | relayrl / SB3 speed | final relayrl | SB3 |")
    print("|---|---|---|---|---|---|")
    for seed in args.seeds:
        out = {}
        for which, python in (("relayrl", sys.executable), ("sb3", args.peer_python)):
            result, proc = run_worker(python, __file__, [which, str(seed), str(args.steps), str(args.threads)])
            if result is None:
                raise RuntimeError(f"{which} worker failed:\n{proc.stderr[-3000:]}")
            out[which] = result
        ours, peer = out["relayrl"], out["sb3"]
        speed = peer["wall_s"] / ours["wall_s"]
        ratios.append(speed)
        results[str(seed)] = out
        print(f"| {seed} | {args.steps / ours['wall_s']:.1f} ({ours['eval_s']:.1f}) | "
              f"{args.steps / peer['wall_s']:.1f} ({peer['eval_s']:.1f}) | {speed:.2f}x | "
              f"{ours['final']:.1f} | {peer['final']:.1f} |", flush=True)
    finals = {w: [results[s][w]["final"] for s in results] for w in ("relayrl", "sb3")}
    print(f"mean speed-up {statistics.mean(ratios):.2f}x; final return relayrl "
          f"{statistics.mean(finals['relayrl']):.1f}, SB3 {statistics.mean(finals['sb3']):.1f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
