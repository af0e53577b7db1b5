#!/usr/bin/env bash
# The planner's search size with the perfect world model (the synthetic
# world's own renderer): reach success per CEM setting at about 400 model
# evaluations per trial, the budget a trained model affords in 30 minutes per
# task on a 2-core CPU (issue 19). One table row per setting.
#
# Usage: scripts/experiments/cem-size-sweep.sh [BINARY]   (default target/release/bridgev2w)
set -euo pipefail
cd "$(dirname "$0")/../.."
BIN=${1:-target/release/bridgev2w}
TMP=$(mktemp -d)
trap 'rm -rf "$TMP"' EXIT
echo "| samples | elites | iters | max actions | translation std (m) | evaluations per trial (at most) | reach success | mean error (cm) | random mean error (cm) | mean actions | time (s) |"
echo "|---|---|---|---|---|---|---|---|---|---|---|"
# samples elites iters max-steps translation-std-m
for cfg in "16 4 1 15 0.1" "24 4 1 15 0.1" "32 4 1 12 0.1" "16 4 2 12 0.1" "12 3 2 15 0.1" "8 2 3 15 0.1" \
    "16 4 1 25 0.1" "12 3 1 30 0.1" "8 2 1 45 0.1" "12 3 1 30 0.05" "16 4 1 25 0.05" \
    "16 4 1 25 0.03" "16 4 1 25 0.04" "24 4 1 20 0.05" "16 4 1 30 0.05" "8 2 2 25 0.05"; do
    set -- $cfg
    "$BIN" plan-report --models perfect --tasks reach --section sweep --trials 20 \
        --samples "$1" --elites "$2" --iters "$3" --horizon 1 --keep-elites --execute-best \
        --max-steps "$4" --translation-std-m "$5" --waypoints 2 --eval-trials 1 \
        --out "$TMP/sweep.md" >"$TMP/log" 2>&1
    # | reach | perfect | 13/20 | 0/20 | 11.1 | 43.0 | 18.0 | 136 |
    row=$(grep '^| reach' "$TMP/sweep.md")
    IFS='|' read -r _ _ _ ok _ err rerr acts secs _ <<<"$row"
    echo "| $1 | $2 | $3 | $4 | $5 | $(($1 * $3 * $4)) |$ok|$err|$rerr|$acts|$secs|"
    rm -f "$TMP/sweep.md"
done
