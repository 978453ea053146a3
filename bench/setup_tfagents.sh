#!/usr/bin/env bash
# TF-Agents DQN tutorial peer (bench/tfagents_dqn_tutorial.py), for benchmarks only: its own venv
# outside the repo, never a relayrl dependency. Usage: bash bench/setup_tfagents.sh [VENV]
set -euo pipefail
VENV="${1:-/work/benchvenv-tfa}"
python3.11 -m venv "$VENV"
"$VENV/bin/pip" install -q --upgrade pip
# tensorflow-cpu instead of the `tensorflow` wheel that tf-agents[reverb] would pull (same 2.15.1
# code, half the size); everything else tf-agents 0.19.0 requires is named here, so it goes in
# with --no-deps and `pip check` stays clean. gym<=0.23.0 is tf-agents' own bound; pygame is
# imported at module level by gym 0.23's CartPole even without rendering.
"$VENV/bin/pip" install -q "tensorflow-cpu==2.15.1" "tf-keras==2.15.0" \
    "tensorflow-probability==0.23.0" "dm-reverb==0.14.0" "gym==0.23.0" "pygame==2.1.3" \
    "numpy<2" "typing-extensions==4.5.0" absl-py cloudpickle gin-config pillow six protobuf wrapt
"$VENV/bin/pip" install -q --no-deps "tf-agents==0.19.0"
"$VENV/bin/pip" check
"$VENV/bin/python" -c "import tensorflow, reverb, tf_agents; from tf_agents.environments import suite_gym; suite_gym.load('CartPole-v0'); print('tf', tensorflow.__version__, 'tf-agents', tf_agents.__version__)"
echo "TF-Agents peer installed in $VENV"
