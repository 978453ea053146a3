#!/bin/sh
# Same-run A/B of two source trees on a lent GPU: `bench/gpu.py --only RUN` for each run, the
# base tree first and then this one, ROUNDS times; one JSON line each, prefixed with the tree
# and the run, to $OUT/ab.txt (or the current folder) and stdout.
#
#     mkdir -p .base && git archive BASE_REV src | tar -x -C .base   # here; .base/ is ignored
#     sh bench/gpu_ab.sh ROUNDS RUN...        # a device call with carry [".whl", ".base"]
set -u
out="${OUT:-.}"
[ -d .base/src ] || { echo "no .base/src: mkdir -p .base && git archive BASE_REV src | tar -x -C .base"; exit 2; }
. bench/gpu_site.sh
rounds="$1"; shift
for _ in $(seq "$rounds"); do
    for run in "$@"; do
        for tree in .base/src src; do
            PYTHONPATH="/tmp/site:$(pwd)/$tree" python3 bench/gpu.py --only "$run" --seconds 8 \
                --out "$out/ab-last.json" 2>"$out/ab-stderr.txt" | grep "^{" | sed "s|^|$tree $run |" \
                | tee -a "$out/ab.txt" || tail -5 "$out/ab-stderr.txt"  # a broken run says why
        done
    done
done
