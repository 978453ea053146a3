#!/usr/bin/env bash
# Peers for benchmarks only, in their own venv (never project dependencies).
set -euo pipefail
cd "$(dirname "$0")"
python3 -m venv .venv-peers
.venv-peers/bin/pip install -q torch==2.13.0
# box2d: LunarLander-v3 for bench/ppo.py
.venv-peers/bin/pip install -q "stable-baselines3==2.*" "gymnasium[classic-control,box2d]>=1.0" "torchrl==0.14.1"
echo "peers installed in bench/.venv-peers"
