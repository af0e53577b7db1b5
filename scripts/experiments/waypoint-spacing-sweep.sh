#!/usr/bin/env bash
# Where the waypoint goal images go (`--waypoints N`: N evenly spaced expert
# frames before each key goal; `--waypoint-every-m M`: one about every M
# metres of the expert's TCP path) with the perfect world model on the
# *train* split, at the search size a trained model affords here (S 16 / k 4
# / T 1, at most 25 actions, std 0.05 m, view margin 0.2): one line per task,
# seed and spacing (issue 19, session 36; log
# docs/results/logs/plan-perfect-waypoint-spacing-train-r36.log).
#
# Usage: scripts/experiments/waypoint-spacing-sweep.sh [BINARY] [TASKS] [SEEDS] [SPACINGS]
#   defaults: target/release/bridgev2w, "reach push pick_place", "0 1",
#   "n2 n3 m0.08 m0.12 m0.16" (nN: --waypoints N; mM: --waypoint-every-m M)
set -euo pipefail
cd "$(dirname "$0")/../.."
BIN=${1:-target/release/bridgev2w}
TASKS=${2:-reach push pick_place}
SEEDS=${3:-0 1}
SPACINGS=${4:-n2 n3 m0.08 m0.12 m0.16}
for task in $TASKS; do
    for seed in $SEEDS; do
        for s in $SPACINGS; do
            case $s in
                n*) spacing=(--waypoints "${s#n}") ;;
                m*) spacing=(--waypoint-every-m "${s#m}") ;;
                *) echo "unknown spacing $s (expected nN or mM)" >&2; exit 2 ;;
            esac
            echo "== $task, seed $seed, ${spacing[*]}"
            "$BIN" plan --task "$task" --trials 20 --model perfect --samples 16 --elites 4 \
                --iters 1 --horizon 1 --keep-elites --execute-best --max-steps 25 \
                --translation-std-m 0.05 --view-margin 0.2 --split train --seed "$seed" \
                "${spacing[@]}" 2>&1 | tail -1
        done
    done
done
