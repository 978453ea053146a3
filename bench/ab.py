"""Same-run A/B of two relayrl source trees (e.g. a change against the commit before it).

    python bench/ab.py --a /path/to/base-checkout --b . [--rounds 3] [--only dqn-zoo per]
        [--json bench/results/ab.json]

Each workload runs in fresh processes, alternating A, B, A, B, ... so both trees see the same
machine load; each tree runs its own bench script (so a renamed import on one side is no
matter) with `PYTHONPATH=<tree>/src`. The table reports medians and B relative to A, where
> 1.00 means B is faster. Workloads:

  dqn-zoo     bench/dqn_cartpole.py's relayrl zoo setting, seed 0 (50,000 env steps): wall-clock of
              the training loop, evaluation excluded (a change of random streams changes episode
              lengths, so evaluation time is not the code's)
  sac         bench/sac_pendulum.py's relayrl side, seed 0, --sac-steps env steps: as dqn-zoo
  collect-32  bench/collect.py --envs 32 --vectorization sync (SAC's actor, 32 Pendulum copies,
              writer and table): env steps/s
  ppo-cartpole     bench/ppo.py's relayrl cartpole setting, seed 0, --ppo-cartpole-steps env steps:
                   as dqn-zoo
  ppo-lunarlander  bench/ppo.py's relayrl lunarlander setting, seed 0, --ppo-lunarlander-steps: as dqn-zoo
  per         bench/replay.py's relayrl `per` task (prioritized sample 256 + update from a
              1,000,000-item table): iterations/s
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

# name -> (argv after the tree's python, how to read the figure, "time" (lower is better) or "rate")
Workload = tuple[Callable[[argparse.Namespace, Path], list[str]], Callable[[str, Path], float], str]


def _result(stdout: str, _: Path) -> dict:
    for line in stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT "):])
    raise RuntimeError("no RESULT line")


def _train_s(result: dict) -> float:
    return result["wall_s"] - result["eval_s"]


def _collect_json(_: str, out: Path) -> float:
    return json.loads(out.read_text())["rows"][0]["ours_sps"]


WORKLOADS: dict[str, Workload] = {
    "dqn-zoo": (lambda a, out: ["bench/dqn_cartpole.py", "--worker", "relayrl", "zoo", "0"],
                lambda s, out: _train_s(_result(s, out)), "time"),
    "sac": (lambda a, out: ["bench/sac_pendulum.py", "--worker", "relayrl", "0", str(a.sac_steps), "-1"],
            lambda s, out: _train_s(_result(s, out)), "time"),
    "collect-32": (lambda a, out: ["bench/collect.py", "--envs", "32", "--vectorization", "sync", "--repeats", "1",
                                   "--seconds", str(a.seconds), "--json", str(out)], _collect_json, "rate"),
    "ppo-cartpole": (lambda a, out: ["bench/ppo.py", "--worker", "relayrl", "cartpole", "0",
                                     str(a.ppo_cartpole_steps), "0"], lambda s, out: _train_s(_result(s, out)), "time"),
    "ppo-lunarlander": (lambda a, out: ["bench/ppo.py", "--worker", "relayrl", "lunarlander", "0",
                                        str(a.ppo_lunarlander_steps), "0"], lambda s, out: _train_s(_result(s, out)),
                        "time"),
    "per": (lambda a, out: ["bench/replay.py", "--worker", "relayrl", "per", str(a.seconds)],
            lambda s, out: _result(s, out)["rate"], "rate"),
}


def run_once(tree: Path, name: str, args: argparse.Namespace) -> float:
    argv, read, _ = WORKLOADS[name]
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "out.json"
        env = {**os.environ, "PYTHONPATH": str(tree / "src")}
        proc = subprocess.run([sys.executable, *argv(args, out)], cwd=tree, env=env, capture_output=True, text=True,
                              check=False)
        if proc.returncode != 0:
            raise RuntimeError(f"{name} in {tree} failed:\n{proc.stderr[-3000:]}")
        return read(proc.stdout, out)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--a", required=True, type=Path, help="the baseline tree (a checkout of the commit before)")
    p.add_argument("--b", default=Path("."), type=Path, help="the tree under test")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--only", nargs="+", choices=sorted(WORKLOADS), default=list(WORKLOADS))
    p.add_argument("--sac-steps", type=int, default=4000)
    p.add_argument("--ppo-cartpole-steps", type=int, default=25_600)
    p.add_argument("--ppo-lunarlander-steps", type=int, default=32_768)
    p.add_argument("--seconds", type=float, default=2.0, help="timed length of the rate workloads")
    p.add_argument("--json")
    args = p.parse_args()
    trees = {"A": args.a.resolve(), "B": args.b.resolve()}
    figures: dict[str, dict[str, list[float]]] = {n: {"A": [], "B": []} for n in args.only}
    for name in args.only:
        for r in range(args.rounds):
            for side in ("A", "B") if r % 2 == 0 else ("B", "A"):
                figures[name][side].append(run_once(trees[side], name, args))
            print(f"{name} round {r + 1}: A {figures[name]['A'][-1]:.4g}, B {figures[name]['B'][-1]:.4g}",
                  file=sys.stderr, flush=True)
    print(f"A = {trees['A']}\nB = {trees['B']}\n")
    print("| workload | unit | A median | B median | B vs A (> 1: B faster) | A rounds | B rounds |")
    print("|---|---|---|---|---|---|---|")
    for name in args.only:
        kind = WORKLOADS[name][2]
        a, b = (statistics.median(figures[name][s]) for s in ("A", "B"))
        speed = a / b if kind == "time" else b / a
        unit = "s (wall-clock)" if kind == "time" else "per s"
        print(f"| {name} | {unit} | {a:.4g} | {b:.4g} | {speed:.3f} | "
              f"{', '.join(f'{x:.4g}' for x in figures[name]['A'])} | "
              f"{', '.join(f'{x:.4g}' for x in figures[name]['B'])} |")
    if args.json:
        Path(args.json).write_text(json.dumps({"trees": {k: str(v) for k, v in trees.items()},
                                               "figures": figures}, indent=1))


if __name__ == "__main__":
    main()
