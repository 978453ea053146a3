"""PPO's env steps/s on the stateless torch Pendulum against Gymnasium Pendulum-v1 copies, same run.

    .venv/bin/python bench/ppo_stateless.py [--steps 163840] [--repeats 3] [--json out.json]

Both paths run the `ppo-stateless-pendulum` preset's agent settings and env count (1,024)
on the CPU, each run a fresh process, alternating: `stateless` (env, policy, rollout and GAE
as torch tensors) and `gym` (`env.id=Pendulum-v1`: 1,024 Gymnasium copies, sync, NumPy
rollouts). `whole loop` is training as the preset runs it; `collection only` is the same run
with `train.gradient_steps=0` (env + collect policy + metrics + rollout writer). steps/s =
env steps / (wall-clock time - evaluation time), from the run's metrics.jsonl.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

WORKER = r'''
import json, sys, relayrl
from relayrl.training.run_dir import RunDir
over, path = json.loads(sys.argv[1]), sys.argv[2]
relayrl.train(relayrl.load_config("ppo-stateless-pendulum", over, seed=0), path, progress=False)
rows = RunDir(path).read_metrics()
busy = rows[-1]["wall_time_s"] - sum(r["eval_s"] for r in rows)
print(json.dumps({"steps": rows[-1]["step"], "sps": rows[-1]["step"] / busy}))
'''
MODES = {"stateless": [], "gym": ["env.id=Pendulum-v1"]}
LOOPS = {"whole loop": [], "collection only": ["train.gradient_steps=0"]}


def one(over: list[str], path: Path) -> float:
    p = subprocess.run([sys.executable, "-c", WORKER, json.dumps(over), str(path)], capture_output=True, text=True,
                       env=os.environ)
    if p.returncode:
        raise SystemExit(p.stderr[-3000:])
    return float(json.loads(p.stdout.strip().splitlines()[-1])["sps"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=163_840)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    base = ["device=cpu", f"train.total_steps={a.steps}", f"eval.interval={10 * a.steps}", "eval.episodes=4",
            "train.checkpoint_interval=0", "train.policy_save_interval=0"]
    out: dict[str, dict[str, list[float]]] = {loop: {m: [] for m in MODES} for loop in LOOPS}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(a.repeats):
            for loop, lo in LOOPS.items():
                for mode, mo in MODES.items():
                    sps = one(base + lo + mo, Path(tmp) / f"{len(out[loop][mode])}-{mode}-{loop[0]}")
                    out[loop][mode].append(sps)
                    print(f"{loop:16s} {mode:9s} repeat {r}: {sps:10,.0f} env steps/s", flush=True)
    for loop, modes in out.items():
        s, g = (statistics.median(modes[m]) for m in MODES)
        print(f"{loop:16s} median stateless {s:,.0f} | gym {g:,.0f} | ratio {s / g:.2f}")
    if a.json:
        a.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
