#!/usr/bin/env bash
# The view limit (`--view-margin F`: planned and random moves stop where the
# TCP would come within F of the image's smaller side of its edges) with the
# perfect world model on the *train* split's reach instances, at the search
# size a trained model affords here (S 16 / k 4 / T 1, at most 25 actions,
# std 0.05 m): one line per seed and margin (issue 19, session 31; log
# docs/results/logs/view-margin-perfect-train-r31.log).
#
# Usage: scripts/experiments/view-margin-sweep.sh [BINARY] [SEEDS] [MARGINS]
#   defaults: target/release/bridgev2w, "0 1", "none 0.05 0.1 0.15 0.2 0.25 0.3"
set -euo pipefail
cd "$(dirname "$0")/../.."
BIN=${1:-target/release/bridgev2w}
SEEDS=${2:-0 1}
MARGINS=${3:-none 0.05 0.1 0.15 0.2 0.25 0.3}
for seed in $SEEDS; do
    for m in $MARGINS; do
        extra=()
        [[ $m != none ]] && extra=(--view-margin "$m")
        echo "== seed $seed, view margin $m"
        "$BIN" plan --task reach --trials 20 --model perfect --samples 16 --elites 4 --iters 1 \
            --horizon 1 --keep-elites --execute-best --max-steps 25 --translation-std-m 0.05 \
            --waypoints 2 --split train --seed "$seed" "${extra[@]}" 2>&1 | tail -1
    done
done
