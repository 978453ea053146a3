#!/bin/sh
# Why pixel DQN learns on a CPU but dqn-pong-fast learned nothing on a GPU (docs/benchmarks.md,
# "dqn-pong-fast"), in one call of the device tool (at most ~8 minutes; carry [".whl"],
# timeout_s 600):
#
#     sh bench/gpu_diagnose.sh
#
# 1. tests/test_graphed.py, with the CUDA tests of the pixel path: the Nature CNN's graphed
#    update against the same update launched kernel by kernel, as the Learner drives it; the
#    graphed greedy policy on pinned frames in inference mode.
# 2. bench/gpu_pixels.py: PixelCatch on CUDA as shipped and with each CUDA-only path turned off
#    in turn, then on the CPU (evaluations and training episodes); the variant that learns where
#    the shipped one does not names the broken path.
# 3. bench/gpu_policies.py: a 30,000-step dqn-pong-fast run, then its collect and evaluation
#    policies against its networks run eagerly, on fresh Pong frames.
# Output: tests-graphed.txt, pixels.txt and policies.txt in $OUT (or the current folder).
# `timeout -k`: a run stops at SIGTERM only at its next safe point, so each step is also killed.
set -u
out="${OUT:-.}"
. bench/gpu_site.sh
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
timeout -k 10 80 python3 -m pytest -q -p no:cacheprovider -m "not slow" tests/test_graphed.py \
    >"$out/tests-graphed.txt" 2>&1
tail -5 "$out/tests-graphed.txt"
timeout -k 10 300 python3 bench/gpu_pixels.py --timeout 55 \
    --variants shipped no-graphs host-replay no-graphs-host-replay cpu | tee "$out/pixels.txt"
timeout -k 10 90 python3 bench/gpu_policies.py 2>"$out/policies-stderr.txt" | tee "$out/policies.txt"
