#!/bin/sh
# The wheels a lent GPU machine lacks for relayrl's benchmarks and tests, in .whl/ (git-ignored
# through .git/info/exclude, never committed). That machine has Python 3.12 and torch with CUDA,
# NumPy, OpenCV, matplotlib, tensorboard, tqdm, cloudpickle and pytest, but not Gymnasium,
# ale-py or tomli-w; nothing can be downloaded there.
#
#     sh bench/gpu_wheels.sh            # from the repository root; then, with the device tool:
#     run(carry=[".whl"], timeout_s=600, command="python3 -m pip install -q --no-index --no-deps \
#         --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl && \
#         export PYTHONPATH=/tmp/site:src PYTHONUNBUFFERED=1 || exit; python3 bench/gpu.py --smoke && \
#         python3 bench/gpu.py --out $OUT/gpu.json")
set -eu
cd "$(git rev-parse --show-toplevel)"
exclude="$(git rev-parse --git-path info/exclude)"
mkdir -p "$(dirname "$exclude")"
grep -qx '/.whl/' "$exclude" 2>/dev/null || echo '/.whl/' >>"$exclude"
# --no-deps: each package relayrl needs beyond that machine's image is named here, one version each.
python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 --platform manylinux1_x86_64 --platform any -d .whl \
    gymnasium==1.4.0 farama-notifications==0.0.6 ale-py==0.12.1 tomli-w==1.2.0
du -sh .whl
