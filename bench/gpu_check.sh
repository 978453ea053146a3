#!/bin/sh
# Every GPU check in one call (~6-8 minutes on one H100; at most 560 s): the CUDA tests, the smoke (train,
# evaluate, export and load each algorithm on CUDA) and bench/gpu.py's table with its A/Bs.
# Run here first: sh bench/gpu_wheels.sh. Then one call of the device tool, from the repository
# root, with carry [".whl"] and timeout_s 600:
#
#     sh bench/gpu_check.sh
#
# What it writes goes to $OUT (tests.txt, tests-compiled.txt, smoke.txt, bench.txt, gpu.json), or
# to the current folder where OUT is unset. A profile of a run and where runs wait for the GPU are separate
# calls: `python3 bench/gpu.py --profile ppo-stateless-pendulum --seconds 10` and
# `python3 bench/gpu.py --syncs ppo-stateless-pendulum ddqn-pong sac-pendulum --seconds 4`.
set -u
out="${OUT:-.}"
. bench/gpu_site.sh
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
python3 -c "import torch; print('torch', torch.__version__)"
timeout 80 python3 -m pytest -q -p no:cacheprovider -m "not slow" tests/test_graphed.py tests/test_ale_vector.py \
    tests/test_bench_gpu.py tests/test_stateless.py::test_adapter_graphed_on_cuda_steps_as_launched_op_by_op \
    >"$out/tests.txt" 2>&1
tail -3 "$out/tests.txt"
# inductor's first compiles on a fresh machine: a step of their own, so a slow one cuts nothing else
timeout 70 python3 -m pytest -q -p no:cacheprovider -m "not slow" tests/test_compiled_losses.py \
    >"$out/tests-compiled.txt" 2>&1
tail -3 "$out/tests-compiled.txt"
timeout 80 python3 bench/gpu.py --smoke >"$out/smoke.txt" 2>&1
grep -E '^(PASS|FAIL|SKIP)' "$out/smoke.txt"
timeout 330 python3 bench/gpu.py --seconds 10 --out "$out/gpu.json" >"$out/bench.txt" 2>&1
grep -vE '^step |callback returned False' "$out/bench.txt" | tail -30
