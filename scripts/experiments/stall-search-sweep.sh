#!/usr/bin/env bash
# What the planner does on a stalled step, with the perfect world model at the
# search size a trained model affords here (S 16 / k 4 / T 1, at most 25
# actions, std 0.05 m, view margin 0.2, a waypoint every 0.12 m): whether
# staying put is a candidate (`--include-mean`), how many stalled steps a
# waypoint gets (`--subgoal-patience`) and how much finer each retry searches
# (`--shrink-on-stall`). One line per task, seed and variant (issue 19,
# session 37; log docs/results/logs/plan-perfect-stall-search-SPLIT-r37.log).
#
# Usage: scripts/experiments/stall-search-sweep.sh [BINARY] [SPLIT] [TASKS] [SEEDS] [VARIANTS]
#   defaults: target/release/bridgev2w, train, "reach push pick_place", "0 1",
#   "base mean mean-p2-s0.5 mean-p3-s0.5 mean-p2-s0.3 p2-s0.5"
#   (a variant is words joined by '-': mean = --include-mean, pN =
#   --subgoal-patience N, sF = --shrink-on-stall F, aN = --max-steps N
#   instead of 25, SN = --samples N instead of 16, release =
#   --release-before-final (session 38); base: none of them)
set -euo pipefail
cd "$(dirname "$0")/../.."
BIN=${1:-target/release/bridgev2w}
SPLIT=${2:-train}
TASKS=${3:-reach push pick_place}
SEEDS=${4:-0 1}
VARIANTS=${5:-base mean mean-p2-s0.5 mean-p3-s0.5 mean-p2-s0.3 p2-s0.5}
for task in $TASKS; do
    for seed in $SEEDS; do
        for v in $VARIANTS; do
            flags=()
            steps=25
            samples=16
            IFS=- read -r -a words <<<"$v"
            for w in "${words[@]}"; do
                case $w in
                    base) ;;
                    mean) flags+=(--include-mean) ;;
                    release) flags+=(--release-before-final) ;;
                    p*) flags+=(--subgoal-patience "${w#p}") ;;
                    s*) flags+=(--shrink-on-stall "${w#s}") ;;
                    a*) steps=${w#a} ;;
                    S*) samples=${w#S} ;;
                    *) echo "unknown variant word $w in $v" >&2; exit 2 ;;
                esac
            done
            echo "== $task, seed $seed, $v: ${flags[*]} --max-steps $steps --samples $samples"
            "$BIN" plan --task "$task" --trials 20 --model perfect --samples "$samples" --elites 4 \
                --iters 1 --horizon 1 --keep-elites --execute-best --max-steps "$steps" \
                --translation-std-m 0.05 --view-margin 0.2 --waypoint-every-m 0.12 \
                --split "$SPLIT" --seed "$seed" "${flags[@]}" 2>&1 | tail -1
        done
    done
done
