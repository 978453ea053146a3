#!/bin/sh
# A Pong preset's target (greedy evaluation >= +18 within 15 minutes of wall-clock, from a fresh
# start) on a lent GPU, whose calls last at most 10 minutes each: the run starts detached and a
# second call, right after the first, waits for it. The target is met at the first evaluation
# >= 18 with wall_time_s <= 900, so the wait ends there.
#
#     sh bench/gpu_pong.sh start [PRESET [ARGS...]]  # call 1 (carry [".whl"]): returns at once; PRESET
#                                                    # ppo-pong (default) or dqn-pong-fast, ARGS more
#                                                    # of relayrl train's (--seed 1)
#     sh bench/gpu_pong.sh wait SECONDS              # call 2, on the same warm machine
set -u
run=/tmp/pong-run
case "${1:-}" in
start)
    . bench/gpu_site.sh
    preset="${2:-ppo-pong}"
    shift; [ $# -gt 0 ] && shift
    setsid python3 -m relayrl train "$preset" --run-dir "$run" --no-progress "$@" \
        >/tmp/pong.log 2>&1 </dev/null &
    echo $! >/tmp/pong.pid
    echo "started $preset $*: $run" ;;
wait)
    end=$(( $(date +%s) + ${2:-540} ))
    while [ "$(date +%s)" -lt "$end" ]; do
        if python3 - "$run/metrics.jsonl" <<'PY'
import json, sys
rows = [json.loads(line) for line in open(sys.argv[1])] if __import__("os").path.exists(sys.argv[1]) else []
evals = [(r["step"], r["average_return"], r["wall_time_s"]) for r in rows if "average_return" in r]
print("evaluations (step, return, s):", evals[-3:], flush=True)
sys.exit(0 if any(ret >= 18 and t <= 900 for _, ret, t in evals) else 1)
PY
        then echo "target met"; break; fi
        if [ -f /tmp/pong.pid ] && ! kill -0 "$(cat /tmp/pong.pid)" 2>/dev/null; then
            echo "the run has ended"; break
        fi
        sleep 20
    done
    cp "$run/metrics.jsonl" "${OUT:-.}/pong-metrics.jsonl" 2>/dev/null
    cp /tmp/pong.log "${OUT:-.}/pong.log" 2>/dev/null; tail -3 /tmp/pong.log ;;
*)
    echo "usage: sh bench/gpu_pong.sh start [PRESET [ARGS...]] | wait SECONDS"; exit 2 ;;
esac
