"""Whether a run's collect and evaluation policies act as its online network does, on the run's
own frames: a short `dqn-pong-fast` run (or another preset), then, on fresh frames of its env,
the greedy actions of the collect policy's network (the acting copy, graphed forward on CUDA),
of the evaluation policy (the online network, graphed forward) and of both networks run eagerly,
and how far the acting copy's weights are from the online network's.

    python bench/gpu_policies.py [--preset dqn-pong-fast] [--steps 30000] [--device cuda]

With everything right every count of differing actions is 0 and the weights are equal (the
acting copy pulls them every collect call; the script pulls once more after training). One
JSON line. `dqn-pong-fast`'s 30,000 steps take ~30 s on a GPU; `--steps 600 --device cpu`
checks the script on a CPU.
"""

from __future__ import annotations

import argparse
import json
import tempfile

import torch

from relayrl.config import Config
from relayrl.envs import make_env
from relayrl.presets import load_config
from relayrl.training.local import LocalDriver
from relayrl.training.run_dir import RunDir


def short_config(preset: str, steps: int, device: str) -> Config:
    c = load_config(preset, [f"train.total_steps={steps}", f"train.initial_collect_steps={min(5_000, steps // 3)}",
                             f"agent.epsilon_decay_steps={steps // 3}", "eval.interval=0", "eval.episodes=2",
                             "train.policy_save_interval=0", "train.log_interval=0", f"device={device}"])
    c.replay.size = min(c.replay.size, max(steps, 1_000))
    return c


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", default="dqn-pong-fast")
    p.add_argument("--steps", type=int, default=30_000)
    p.add_argument("--device", default="cuda")
    p.add_argument("--frames", type=int, default=200, help="batched env steps of fresh frames to compare on")
    args = p.parse_args()
    c = short_config(args.preset, args.steps, args.device)
    with tempfile.TemporaryDirectory() as tmp:
        driver = LocalDriver(c, RunDir(tmp), progress=False)
        driver.train()
        collect = driver.collect_policy.greedy
        agent = driver.agent
        evaluation = agent.eval_policy()
        acting, online = collect.q_net, agent.online
        driver.actor.puller.maybe_pull(driver.actor.env_steps)  # as the next collect call would: the newest weights
        with torch.no_grad():
            weight_gap = max(float((a - b).abs().max()) for a, b in zip(acting.parameters(), online.parameters(),
                                                                          strict=True))
        env = make_env(c.env.id, c.env.num_envs, vectorization=c.env.vectorization, device=driver.device)
        obs = env.reset(seed=123)
        counts = {"collect_vs_eager_acting": 0, "eval_vs_eager_online": 0, "collect_vs_eval": 0,
                  "eager_acting_vs_eager_online": 0}
        actions_seen: set[int] = set()
        q_spread = 0.0
        g = torch.Generator().manual_seed(0)
        for _ in range(args.frames):
            with torch.no_grad():
                x = obs.to(driver.device)
                q_acting, q_online = acting(x), online(x)
                a_acting, a_online = q_acting.argmax(1).cpu(), q_online.argmax(1).cpu()
                a_collect = collect(obs)
            with torch.inference_mode():
                a_eval = evaluation(obs)
            counts["collect_vs_eager_acting"] += int((a_collect != a_acting).sum())
            counts["eval_vs_eager_online"] += int((a_eval != a_online).sum())
            counts["collect_vs_eval"] += int((a_collect != a_eval).sum())
            counts["eager_acting_vs_eager_online"] += int((a_acting != a_online).sum())
            actions_seen.update(a_online.tolist())
            q_spread += float((q_online.max(1).values - q_online.min(1).values).mean()) / args.frames
            obs = env.step(torch.randint(0, int(q_online.shape[1]), (env.num_envs,), generator=g)).obs
        env.close()
        print(json.dumps({"preset": args.preset, "device": str(driver.device), "steps": args.steps,
                          "train_steps": agent.train_step, "compared_actions": args.frames * env.num_envs,
                          "differing": counts, "acting_vs_online_max_weight_gap": weight_gap,
                          "online_greedy_actions_seen": sorted(actions_seen),
                          "online_q_max_minus_min": round(q_spread, 5)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
