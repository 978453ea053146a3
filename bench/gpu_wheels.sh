#!/bin/sh
# The wheels a lent GPU machine lacks for relayrl's benchmarks and tests, in .whl/ (git-ignored
# through .git/info/exclude, never committed). That machine has Python 3.12 and torch with CUDA,
# NumPy, OpenCV, matplotlib, tensorboard, tqdm, cloudpickle and pytest, but not Gymnasium,
# ale-py or tomli-w; nothing can be downloaded there.
#
#     sh bench/gpu_wheels.sh [mario]    # where pip can download, from the repository root; then,
#     sh bench/gpu_check.sh             # on the GPU machine with .whl/ (bench/gpu_site.sh installs it)
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
# `sh bench/gpu_wheels.sh mario` adds the [mario] extra: gym-super-mario-bros (pure Python) and
# nes-py, which ships no wheels: its emulator is compiled here, by a Python 3.12 (g++ needed).
if [ "${1:-}" = mario ]; then
    py312=""
    for candidate in python3.12 $(ls -d "$HOME"/.pyenv/versions/3.12*/bin/python 2>/dev/null); do
        "$candidate" --version >/dev/null 2>&1 && { py312="$candidate"; break; }  # (a pyenv shim may not run)
    done
    [ -n "$py312" ] || { echo "no Python 3.12 here to build nes-py's wheel for the GPU machine's Python"; exit 2; }
    "$py312" -m pip wheel -q --no-deps nes-py==8.2.1 gym-super-mario-bros==7.4.0 -w .whl
fi
du -sh .whl
