#!/usr/bin/env bash
# Runs one fuzz target for a wall-clock budget (the test suite runs each for
# about a second):
#
#   scripts/fuzz.sh TARGET SECONDS      TARGET: mp4, urdf or mesh
#
# mp4 (crates/data/tests/fuzz_mp4.rs) runs for SECONDS itself (FUZZ_SECONDS;
# FUZZ_SEED picks another series of cases). urdf and mesh are proptest
# targets with a fixed number of cases per run and a fresh random seed each
# run: they are rerun until SECONDS have passed. A failure stops the script
# and prints the case (MESH_FUZZ_STRICT=1 also fails on caught parser panics).
set -euo pipefail
cd "$(dirname "$0")/.."
target=${1:?usage: scripts/fuzz.sh TARGET SECONDS (mp4, urdf, mesh)}
seconds=${2:?usage: scripts/fuzz.sh TARGET SECONDS}
[[ $seconds =~ ^[0-9]+$ ]] || { echo "error: SECONDS must be a whole number, got $seconds" >&2; exit 2; }
case "$target" in
  mp4)
    FUZZ_SECONDS=$seconds exec cargo test --release -p bridgev2w-data --test fuzz_mp4 -- --nocapture
    ;;
  urdf | mesh)
    test=${target}_fuzz
    cargo test --release -p bridgev2w-embodiment --test "$test" --no-run
    end=$((SECONDS + seconds))
    runs=0
    while ((SECONDS < end)); do
      cargo test -q --release -p bridgev2w-embodiment --test "$test" >/dev/null
      runs=$((runs + 1))
    done
    echo "fuzz $target: $runs runs of the proptest cases in ${seconds} s, no failure"
    ;;
  *)
    echo "error: unknown fuzz target '$target': expected mp4, urdf or mesh" >&2
    exit 2
    ;;
esac
