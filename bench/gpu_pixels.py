"""Whether DQN learns from pixels on a GPU, path by path: relayrl/PixelCatch-v0 (36x36 frames, the
Nature CNN, 8 copies, 3-step returns, dqn-pong-fast's batches) trained on CUDA as shipped, then
with each CUDA-only path turned off in turn, then on the CPU, each in a fresh process. Random
play scores about -3.5 (of -5..5); every variant should pass 3 by 10,000 env steps, as the CPU
does (tests/test_pixel_catch.py). A variant that learns where the shipped one does not names the
path that breaks learning.

    python bench/gpu_pixels.py [--steps 10000] [--variants shipped no-graphs host-replay cpu]

About 20-40 s a variant on one GPU (the CPU variant: ~30 s on 16 cores). One line of JSON per
variant: its greedy evaluations' returns, the training episodes' mean returns at the same steps
(these stay near -3.5 where the collect policy does not act with the learner's weights, even
while the evaluations rise), the last evaluation, and its wall-clock seconds.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

# name: (device, extra environment, replay.device)
VARIANTS: dict[str, tuple[str, dict[str, str], str]] = {
    "shipped": ("cuda", {}, "auto"),  # CUDA graphs on, frames on the GPU
    "no-graphs": ("cuda", {"RELAYRL_CUDA_GRAPHS": "0"}, "auto"),  # updates and forwards kernel by kernel
    "host-replay": ("cuda", {}, "numpy"),  # frames in host arrays, batches copied over
    "no-graphs-host-replay": ("cuda", {"RELAYRL_CUDA_GRAPHS": "0"}, "numpy"),
    "compiled": ("cuda", {"RELAYRL_COMPILE": "1"}, "auto"),
    "cpu": ("cpu", {}, "numpy"),
}


def config(device: str, replay_device: str, steps: int) -> dict:
    return {
        "algo": "dqn", "seed": 0, "device": device,
        "env": {"id": "relayrl/PixelCatch-v0", "num_envs": 8},
        "train": {"total_steps": steps, "initial_collect_steps": 1000, "collect_steps": 8, "gradient_steps": 2,
                  "checkpoint_interval": 0, "log_interval": 0},
        "replay": {"size": 20_000, "n_step": 3, "device": replay_device},
        "eval": {"interval": 2000, "episodes": 8},
        "agent": {"network": "nature_cnn", "lr": 1e-3, "batch_size": 128, "target_update_period": 100,
                  "epsilon_decay_steps": 3000, "epsilon_end": 0.05},
    }


def run_one(name: str, steps: int) -> None:
    import relayrl

    device, _, replay_device = VARIANTS[name]
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        result = relayrl.train(config(device, replay_device, steps), run_dir=f"{tmp}/run", progress=False)
        rows = [json.loads(line) for line in open(result.run_dir / "metrics.jsonl")]
    evals = [row for row in rows if "average_return" in row]
    print(json.dumps({"variant": name, "returns": [row["average_return"] for row in evals],
                      "train_returns": [row["train/average_return"] for row in evals],
                      "last": evals[-1]["average_return"], "wall_s": round(time.perf_counter() - start, 1)}),
          flush=True)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--steps", type=int, default=10_000, help="env steps per variant (default 10000)")
    p.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS))
    p.add_argument("--timeout", type=float, default=120.0, help="seconds a variant may take (default 120)")
    p.add_argument("--one", choices=list(VARIANTS), help=argparse.SUPPRESS)  # a child process's variant
    args = p.parse_args()
    if args.one:
        run_one(args.one, args.steps)
        return 0
    for name in args.variants:
        env = {**os.environ, **VARIANTS[name][1]}
        try:
            done = subprocess.run([sys.executable, __file__, "--one", name, "--steps", str(args.steps)], env=env,
                                  capture_output=True, text=True, timeout=args.timeout)
        except subprocess.TimeoutExpired:
            print(json.dumps({"variant": name, "failed": f"still running after {args.timeout:g} s"}), flush=True)
            continue
        lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
        said = done.stderr.strip().splitlines()[-1:]  # a traceback's last line: what went wrong
        print(lines[-1] if lines else json.dumps({"variant": name, "failed": said}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
