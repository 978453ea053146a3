"""torch_threads per preset: short runs with 1, 2 and 0 (every core) threads, on the machine as
it is and beside one busy process, each in a fresh `relayrl train` process.

    python bench/threads.py [--presets sac-pendulum sac-batched] [--threads 1 2 0] [--rounds 1]

Each row is a preset at a thread count: the run's training wall-clock (metrics.jsonl's last
`wall_time_s` less its evaluations' `eval_s`) quiet and beside one `while True: pass` process,
and busy / quiet as a speed ratio (>= 0.70 is the target for a default on 2 cores). Conditions
alternate (quiet, busy, quiet, ...) so both see the same load from other work; `uptime`'s
load average is printed before and after.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# preset -> --set overrides for a short run of its loop (a few hundred to 2,000 gradient steps)
SHORT = {
    "sac-pendulum": ["train.total_steps=2000", "eval.interval=100000", "eval.episodes=1"],
    "sac-batched": ["train.total_steps=6400", "eval.interval=100000", "eval.episodes=1"],
    "sac-minitaur": ["train.initial_collect_steps=500", "train.total_steps=1500", "eval.interval=100000",
                     "eval.episodes=1"],
    "bptt-pendulum": ["train.total_steps=64000", "eval.interval=100000"],
    "dqn-cartpole-fast": ["train.total_steps=20000", "eval.interval=100000", "eval.episodes=1"],
    "ppo-cartpole": ["train.total_steps=25600", "eval.interval=100000", "eval.episodes=1"],
}


def load() -> str:
    return os.getloadavg().__repr__()


def run(preset: str, threads: int, tmp: Path, timeout: float) -> float:
    """Seconds of training, or `inf` where the run took longer than `timeout` (killed)."""
    run_dir = tmp / f"{preset}-{threads}"
    args = [sys.executable, "-m", "relayrl", "train", preset, "--run-dir", str(run_dir), "--overwrite",
            "--no-progress", "--set", f"train.torch_threads={threads}", "--set", "train.checkpoint_interval=0",
            "--set", "train.policy_save_interval=0"]
    for o in SHORT[preset]:
        args += ["--set", o]
    try:
        subprocess.run(args, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=timeout)
    except subprocess.TimeoutExpired:
        return float("inf")
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    return rows[-1]["wall_time_s"] - sum(r.get("eval_s", 0.0) for r in rows)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--presets", nargs="+", default=["sac-pendulum", "sac-batched"], choices=sorted(SHORT))
    p.add_argument("--threads", nargs="+", type=int, default=[1, 2, 0])
    p.add_argument("--rounds", type=int, default=1)
    p.add_argument("--timeout", type=float, default=120.0, help="a run longer than this is killed: '> T s'")
    p.add_argument("--json")
    a = p.parse_args()
    import torch

    print(f"load average before (1, 5, 15 min): {load()}; {os.cpu_count()} cores; torch_threads=0 runs "
          f"torch's default of {torch.get_num_threads()} threads here", flush=True)
    results: dict[str, dict[str, list[float]]] = {}
    with tempfile.TemporaryDirectory() as d:
        for _ in range(a.rounds):
            for preset in a.presets:
                for threads in a.threads:
                    for busy in (False, True):
                        hog = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if busy else None
                        try:
                            time.sleep(0.5 if busy else 0.0)
                            s = run(preset, threads, Path(d), a.timeout)
                        finally:
                            if hog is not None:
                                hog.kill()
                                hog.wait()
                        key = f"{preset} threads={threads}"
                        results.setdefault(key, {"quiet": [], "busy": []})["busy" if busy else "quiet"].append(s)
                        print(f"{key} {'busy' if busy else 'quiet'}: {s:.1f} s (load {load()})", flush=True)
    print(f"load average after: {load()}")
    print("| preset | torch_threads | quiet s | beside 1 busy process s | busy / quiet speed |")
    print("|---|---|---|---|---|")
    for key, r in results.items():
        preset, threads = key.split(" threads=")
        q, b = min(r["quiet"]), min(r["busy"])
        slow = f"> {a.timeout:.0f}" if b == float("inf") else f"{b:.1f}"
        ratio = f"< {q / a.timeout:.2f}" if b == float("inf") else f"{q / b:.2f}"
        print(f"| {preset} | {threads} | {q:.1f} | {slow} | {ratio} |")
    if a.json:
        Path(a.json).write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
