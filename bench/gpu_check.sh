#!/bin/sh
# Every GPU check in one call (~6 minutes on one H100): the CUDA tests, the smoke (train,
# evaluate, export and load each algorithm on CUDA) and bench/gpu.py's table with its A/Bs.
# Run here first: sh bench/gpu_wheels.sh. Then one call of the device tool, from the repository
# root, with carry [".whl"] and timeout_s 600:
#
#     sh bench/gpu_check.sh
#
# What it writes goes to $OUT (tests.txt, smoke.txt, bench.txt, gpu.json and a profile of the
# stateless PPO loop, profile-ppo-stateless-pendulum.txt, and syncs.txt: where three runs wait
# for the GPU), or to the current folder where OUT is unset.
set -u
out="${OUT:-.}"
. bench/gpu_site.sh
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
python3 -c "import torch; print('torch', torch.__version__)"
timeout 90 python3 -m pytest -q -p no:cacheprovider tests/test_graphed.py tests/test_ale_vector.py \
    tests/test_bench_gpu.py >"$out/tests.txt" 2>&1
tail -3 "$out/tests.txt"
timeout 90 python3 bench/gpu.py --smoke >"$out/smoke.txt" 2>&1
grep -E '^(PASS|FAIL|SKIP)' "$out/smoke.txt"
timeout 300 python3 bench/gpu.py --seconds 10 --out "$out/gpu.json" >"$out/bench.txt" 2>&1
grep -vE '^step |callback returned False' "$out/bench.txt" | tail -30
timeout 45 python3 bench/gpu.py --profile ppo-stateless-pendulum --seconds 10 --out "$out/gpu.json" >/dev/null 2>&1
timeout 60 python3 bench/gpu.py --syncs ppo-stateless-pendulum ddqn-pong sac-pendulum --seconds 4 --out "$out/gpu.json" >"$out/syncs.log" 2>&1
head -12 "$out/syncs.txt"
