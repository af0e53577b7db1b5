#!/usr/bin/env bash
# Runs one fuzz target for a wall-clock budget (the test suite runs each for
# about a second):
#
#   scripts/fuzz.sh TARGET SECONDS
#
# TARGET (the parser it mutates; its test):
#   mp4           MP4 demuxer + H.264 decoding   crates/data/tests/fuzz_mp4.rs
#   npy           .npy arrays                    crates/embodiment/tests/fuzz_inputs.rs
#   camera        camera JSON                    crates/embodiment/tests/fuzz_inputs.rs
#   trajectory    joint/action JSON and CSV      crates/embodiment/tests/fuzz_inputs.rs
#   safetensors   safetensors headers            crates/world-model/tests/fuzz_checkpoint.rs
#   model-config  diffusers config.json          crates/world-model/tests/fuzz_checkpoint.rs
#   train-config  training TOML                  crates/train/tests/fuzz_config.rs
#   lerobot       LeRobot dataset files          crates/data/tests/fuzz_lerobot.rs
#   h5            HDF5 (DROID, AgiBot World)     crates/data/tests/fuzz_h5.rs
#   urdf, mesh    URDF documents, mesh files     crates/embodiment/tests/{urdf,mesh}_fuzz.rs
#
# All but urdf and mesh run for SECONDS themselves (FUZZ_SECONDS; FUZZ_SEED
# picks another series of cases). urdf and mesh are proptest targets with a
# fixed number of cases per run and a fresh random seed each run: they are
# rerun until SECONDS have passed. A failure stops the script and prints the
# case (MESH_FUZZ_STRICT=1 also fails on caught parser panics).
#
# FUZZ_PROFILE picks the cargo profile: release (the default: the most cases
# per second) or dev (the test suite's: it reuses the test build, whose
# features `--workspace` resolves, instead of a release build of its own).
set -euo pipefail
cd "$(dirname "$0")/.."
case "${FUZZ_PROFILE:-release}" in
  release) profile=(--release) ;;
  dev) profile=() ;;
  *)
    echo "error: FUZZ_PROFILE=${FUZZ_PROFILE}: expected release or dev" >&2
    exit 2
    ;;
esac
targets="mp4, npy, camera, trajectory, safetensors, model-config, train-config, lerobot, h5, urdf, mesh"
target=${1:?usage: scripts/fuzz.sh TARGET SECONDS (TARGET: mp4, npy, camera, trajectory, safetensors, model-config, train-config, lerobot, h5, urdf, mesh)}
seconds=${2:?usage: scripts/fuzz.sh TARGET SECONDS}
timed() { # timed PACKAGE TEST [NAME]: a self-timed target
  FUZZ_SECONDS=$seconds exec cargo test "${profile[@]}" --workspace --test "$2" -- --exact "${3:-}" --nocapture
}
case "$target" in
  mp4 | npy | camera | trajectory | safetensors | model-config | train-config | lerobot | h5 | urdf | mesh) ;;
  *)
    echo "error: unknown fuzz target '$target': expected one of $targets" >&2
    exit 2
    ;;
esac
[[ $seconds =~ ^[0-9]+$ ]] || { echo "error: SECONDS must be a whole number, got $seconds" >&2; exit 2; }
case "$target" in
  mp4) timed bridgev2w-data fuzz_mp4 mutated_mp4_files_never_panic_nor_over_allocate ;;
  npy) timed bridgev2w-embodiment fuzz_inputs mutated_npy_files_never_panic_nor_over_allocate ;;
  camera) timed bridgev2w-embodiment fuzz_inputs mutated_camera_json_never_panics_nor_accepts_garbage ;;
  trajectory) timed bridgev2w-embodiment fuzz_inputs mutated_trajectories_never_panic_nor_accept_garbage ;;
  safetensors) timed bridgev2w-world-model fuzz_checkpoint mutated_safetensors_never_panic_nor_reach_libtorch_broken ;;
  model-config) timed bridgev2w-world-model fuzz_checkpoint mutated_model_configs_never_panic_nor_accept_garbage ;;
  train-config) timed bridgev2w-train fuzz_config mutated_training_configs_never_panic_nor_accept_garbage ;;
  lerobot) timed bridgev2w-data fuzz_lerobot mutated_lerobot_datasets_never_panic_nor_over_allocate ;;
  h5) timed bridgev2w-data fuzz_h5 mutated_hdf5_files_never_panic_nor_over_allocate ;;
  urdf | mesh)
    test=${target}_fuzz
    cargo test "${profile[@]}" --workspace --test "$test" --no-run
    end=$((SECONDS + seconds))
    runs=0
    while ((SECONDS < end)); do
      cargo test -q "${profile[@]}" --workspace --test "$test" >/dev/null
      runs=$((runs + 1))
    done
    echo "fuzz $target: $runs runs of the proptest cases in ${seconds} s, no failure"
    ;;
esac
