"""Resume fidelity: runs killed with SIGKILL at random moments and resumed, against the uninterrupted run.

    .venv/bin/python bench/resume_fidelity.py [--preset dqn-cartpole-fast] [--kills 3] [--seed 0]
        [--set KEY=VALUE ...] [--json bench/results/resume.json]

Runs the preset once uninterrupted, then `--kills` times more: each run is killed with SIGKILL
at a uniformly random moment between its first checkpoint and the uninterrupted run's end,
then continued with `relayrl train ... --resume` (again and again if a resume is killed too:
only the first attempt is killed). Prints, per run, where it was killed, the checkpoint it
resumed from, its final evaluation, and whether its metrics.jsonl equals the uninterrupted
run's (timing columns aside). Everything runs through the `relayrl` command, as a user would.
"""

from __future__ import annotations

import argparse
import json
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TIMES = ("wall_time_s", "eval_s")


def rows(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines() if line.strip()]


def comparable(run: Path) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in TIMES} for r in rows(run)]


def train_cmd(args: argparse.Namespace, run: Path) -> list[str]:
    sets = [a for kv in args.set for a in ("--set", kv)]
    return [sys.executable, "-m", "relayrl", "train", args.preset, "--run-dir", str(run), "--seed", str(args.seed),
            "--no-progress", *sets]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="dqn-cartpole-fast")
    ap.add_argument("--kills", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--json")
    args = ap.parse_args()
    rng = random.Random(args.seed)
    root = Path(tempfile.mkdtemp(prefix="resume-fidelity-"))
    t0 = time.perf_counter()
    subprocess.run(train_cmd(args, root / "full"), check=True, stderr=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
    duration = time.perf_counter() - t0
    full = comparable(root / "full")
    print(f"uninterrupted: {duration:.1f} s, final eval {full[-1]['average_return']:.2f} at step {full[-1]['step']}")
    print(f"{'run':>4} {'killed after':>13} {'resumed from':>13} {'final eval':>11} {'identical':>10}")
    results = []
    for k in range(args.kills):
        run = root / f"killed-{k}"
        p = subprocess.Popen(train_cmd(args, run), stderr=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
        start = time.perf_counter()
        while p.poll() is None and not list((run / "checkpoints").glob("ckpt-*.pt")):
            time.sleep(0.01)
        first_ckpt = time.perf_counter() - start
        time.sleep(rng.uniform(0.0, max(0.0, duration - first_ckpt)))
        killed_at = time.perf_counter() - start
        p.send_signal(signal.SIGKILL)
        was_killed = p.wait() == -signal.SIGKILL
        resumed_from = max(int(c.stem.split("-")[1]) for c in (run / "checkpoints").glob("ckpt-*.pt"))
        subprocess.run(train_cmd(args, run) + ["--resume"], check=True, stderr=subprocess.DEVNULL,
                       stdout=subprocess.DEVNULL)
        mine = comparable(run)
        same = mine == full
        final = mine[-1]["average_return"]
        results.append({"killed_after_s": round(killed_at, 2), "killed": was_killed, "resumed_from": resumed_from,
                        "final_eval": final, "identical": same})
        label = f"{killed_at:.1f} s" if was_killed else "(ended)"
        print(f"{k:>4} {label:>13} {resumed_from:>13,} {final:>11.2f} {str(same):>10}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"preset": args.preset, "set": args.set, "seed": args.seed,
                                               "uninterrupted_final": full[-1]["average_return"],
                                               "runs": results}, indent=1))


if __name__ == "__main__":
    main()
