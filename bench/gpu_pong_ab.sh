#!/bin/sh
# Whose is dqn-pong-fast's failure on a GPU (docs/benchmarks.md, "dqn-pong-fast"): relayrl's GPU
# path, relayrl's shared code, or the recipe? One call of the device tool (carry [".whl"],
# timeout_s 600) runs side by side, for SECONDS (default 470) each:
#
#     sh bench/gpu_pong_ab.sh [SECONDS]
#
#   shipped      relayrl train dqn-pong-fast as shipped (CUDA graphs, frames in GPU replay)
#   lapan        Lapan's Pong ratio: one gradient step of batch 32 per env step (4x the shipped
#                recipe's gradient steps, lr 1e-4, a target copy every 1,000 of them) and no
#                sticky actions (env.kwargs.repeat_action_probability=0.0, as NoFrameskip-v4)
#   host-replay  RELAYRL_CUDA_GRAPHS=0 (every kernel launched, as on a CPU) and replay.device=numpy
#                (the CPU's replay; batches copied over): none of the CUDA-only paths
#   reference    bench/pong_reference.py: the same recipe written without relayrl
# and, in its first two minutes, the CUDA tests of tests/test_graphed.py and bench/gpu_policies.py
# (a 30,000-step run's collect and evaluation policies against its networks run eagerly: every
# count should be 0).
#
# Reading it: a variant whose returns climb from random play's -20.5 (greedy evaluations and
# episode lengths move first: on a CPU, -18.2 in 1,345-step episodes while training episodes were
# still at -20.5) where `shipped` stays flat names the broken path; if `reference` climbs and no
# relayrl variant does, the defect is in code every path shares; if only `lapan` climbs, the
# shipped recipe's larger batches (a quarter of the gradient steps) or sticky actions are too
# slow; if nothing climbs, the runs were too short. Four runs share 16 cores and one GPU
# (time-sliced between the processes), so each is slower than alone: learning is compared at
# equal env steps, not speed. Once a path is named, bench/gpu_diagnose.sh narrows it (graphs or
# the GPU replay) on PixelCatch.
# Output in $OUT: pong-VARIANT.log and .jsonl (metrics, copied every 30 s), tests-graphed.txt,
# policies.txt, policies-stderr.txt and summary.txt.
set -u
out="${OUT:-.}"
secs="${1:-470}"
. bench/gpu_site.sh
export OMP_NUM_THREADS=1
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
# The side checks' limits are generous: five CUDA processes start at once, and the trainings
# bound the call anyway.
timeout -k 10 300 python3 -m pytest -q -p no:cacheprovider -m "not slow" tests/test_graphed.py \
    >"$out/tests-graphed.txt" 2>&1 &
pids=$!
timeout -k 10 300 python3 bench/gpu_policies.py >"$out/policies.txt" 2>"$out/policies-stderr.txt" &
pids="$pids $!"
relayrl_run() {  # NAME [VAR=VALUE ...] -- [--set ...]
    name=$1; shift
    vars=""
    while [ "$1" != "--" ]; do vars="$vars $1"; shift; done
    shift
    # shellcheck disable=SC2086
    env $vars timeout -k 20 "$secs" python3 -m relayrl train dqn-pong-fast --run-dir "/tmp/pong-ab/$name" \
        --overwrite --set env.num_workers=2 "$@" >"$out/pong-$name.log" 2>&1 &  # a progress line every 30 s
    pids="$pids $!"
}
relayrl_run shipped --
relayrl_run lapan -- --set env.kwargs.repeat_action_probability=0.0 --set train.gradient_steps=8 \
    --set agent.batch_size=32 --set agent.lr=1e-4 --set agent.target_update_period=1000
relayrl_run host-replay RELAYRL_CUDA_GRAPHS=0 -- --set replay.device=numpy
timeout -k 20 "$secs" python3 bench/pong_reference.py --seconds "$((secs - 15))" --threads 2 \
    >"$out/pong-reference.log" 2>&1 &
pids="$pids $!"
copy_metrics() {  # metrics.jsonl is the training curve: in $OUT as it grows, so a cut call keeps it
    for name in shipped lapan host-replay; do
        cp "/tmp/pong-ab/$name/metrics.jsonl" "$out/pong-$name.jsonl" 2>/dev/null
    done
}
(while sleep 30; do copy_metrics; done) &
copier=$!
# shellcheck disable=SC2086
wait $pids
kill "$copier" 2>/dev/null
copy_metrics
echo "--- tests/test_graphed.py"; tail -3 "$out/tests-graphed.txt"
echo "--- bench/gpu_policies.py"; cat "$out/policies.txt"; tail -2 "$out/policies-stderr.txt"
python3 - "$out" <<'PY' | tee "$out/summary.txt"
import json, os, sys
out = sys.argv[1]
def rows(path):
    return [json.loads(line) for line in open(path) if line.startswith("{")] if os.path.exists(path) else []
for name in ("shipped", "lapan", "host-replay"):
    rs = rows(f"{out}/pong-{name}.jsonl")
    print(f"--- {name}: evaluations (step, training return, evaluation, losses/q, wall s)")
    for r in rs:
        print(" ", r["step"], r.get("train/average_return"), r.get("average_return"),
              None if r.get("losses/q") is None else round(r["losses/q"], 3), r.get("wall_time_s"))
    log = f"{out}/pong-{name}.log"
    progress = [line.strip() for line in open(log) if line.startswith("step ") and "train return" in line] \
        if os.path.exists(log) else []
    print("  progress, every other line:")
    for line in progress[1::2]:
        print("   ", line)
    if not rs:
        print("  no metrics: see", f"pong-{name}.log")
    elif rs[-1]["step"] < 300_000:
        print(f"  inconclusive if flat: {rs[-1]['step']:,} env steps (< 300,000, where a working recipe has risen)")
print("--- reference: step, training return (last 20 episodes), q, s")
ref = rows(f"{out}/pong-reference.log")
for r in ref:
    if "step" in r and r["step"] % 50_000 < 8:
        print(" ", r["step"], r["train_return_last20"], r["q"], round(r["step"] / r["sps"]))
    elif "done" in r:
        print("  end:", r)
steps = [r.get("step", r.get("done", 0)) for r in ref]
if steps and max(steps) < 300_000:
    print(f"  inconclusive if flat: {max(steps):,} env steps (< 300,000)")
PY
