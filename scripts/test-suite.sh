#!/usr/bin/env bash
# The whole test suite (`./run test` with no arguments), in two lanes.
#
# `cargo test` runs one test binary at a time; a binary whose tests are one
# long serial job (a pip build, a Python peer, the GPU checklist's dry run)
# leaves the second core of a 2-core machine idle while it runs. Here the
# test binaries are built once, then the long mostly-serial ones (SLOW_LANE
# below) run in a second `cargo test` beside the others: the same tests, the
# same build, the cores kept busy. The slow lane's output is kept in
# target/test-slow-lane.log and printed when it ends; the suite fails if
# either lane fails.
#
#   scripts/test-suite.sh             build, then both lanes, then the doc tests
#   SLOW_LANE="a b" scripts/...       another choice of slow test binaries
#   TEST_LANES=1 scripts/test-suite.sh  one lane (plain `cargo test --workspace`)
set -euo pipefail
cd "$(dirname "$0")/.."

# Test binaries (cargo test targets, by name) whose wall time is mostly one
# serial job; measured with `./run test` on 2 cores (2026-12-07, seconds,
# the CPU use in cores): python_package 184-367 (1.5), gpu_checklist 140-174
# (1.5), parity_transformer 101-118 (1.6), parity_vae 68-112 (1.1),
# parity_scheduler 81, lerobot_package 41-48 (1.0), prompt_embedding 32-36
# (1.0), lora_export 24-33 (1.0), bridge_predict 27-32 (1.1).
SLOW_LANE="${SLOW_LANE-python_package gpu_checklist parity_transformer parity_vae parity_scheduler lerobot_package prompt_embedding lora_export bridge_predict}"
lanes="${TEST_LANES:-2}"
case "$lanes" in
  1 | 2) ;;
  *)
    echo "test-suite.sh: TEST_LANES=$lanes: expected 1 or 2" >&2
    exit 2
    ;;
esac
if [[ "$lanes" == 1 || -z "$SLOW_LANE" ]]; then
  exec cargo test --workspace
fi

# Every test target of the workspace's packages, by name.
all_tests="$(cargo metadata --no-deps --format-version 1 | python3 -c '
import json, sys
meta = json.load(sys.stdin)
names = sorted({t["name"] for p in meta["packages"] for t in p["targets"] if "test" in t["kind"]})
print(" ".join(names))
')"
slow_args=() fast_args=()
for name in $SLOW_LANE; do
  if [[ " $all_tests " != *" $name "* ]]; then
    echo "test-suite.sh: SLOW_LANE names $name, which is no test target of the workspace" >&2
    exit 2
  fi
  slow_args+=(--test "$name")
done
for name in $all_tests; do
  if [[ " $SLOW_LANE " != *" $name "* ]]; then
    fast_args+=(--test "$name")
  fi
done

# One build of everything `cargo test --workspace` builds (examples and
# benches included), so neither lane compiles and the lanes share it.
cargo test --workspace --no-run

log=target/test-slow-lane.log
echo "test-suite.sh: the slow lane ($SLOW_LANE) runs beside the others; its output: $log" >&2
cargo test --workspace "${slow_args[@]}" >"$log" 2>&1 &
slow_pid=$!
trap 'kill "$slow_pid" 2>/dev/null || true' EXIT INT TERM

status=0
cargo test --workspace --lib --bins "${fast_args[@]}" || status=$?
cargo test --workspace --doc || status=$?

slow_status=0
wait "$slow_pid" || slow_status=$?
trap - EXIT INT TERM
echo "test-suite.sh: the slow lane ($SLOW_LANE), exit status $slow_status:" >&2
cat "$log"
if [[ "$status" != 0 || "$slow_status" != 0 ]]; then
  echo "test-suite.sh: failed (the other tests: exit status $status; the slow lane: $slow_status)" >&2
  exit 1
fi
echo "test-suite.sh: every test passed, in both lanes" >&2
