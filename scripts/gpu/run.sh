#!/usr/bin/env bash
# The GPU checklist (issue 22): every CUDA path of the project measured in
# one go, in parts that each fit the device tool's 10-minute command limit.
# Each item runs under its own time limit and the checklist goes on past a
# failing one; OUT gets logs/, metrics/, items.tsv, summary.json and
# summary.md (the table for docs/benchmarks.md).
#
# Usage: [OUT=DIR] scripts/gpu/run.sh [--dry-run] [--budget SECONDS] [PART|ITEM...]
#   PART: smoke (environment, predict on CUDA vs the CPU, bf16 training,
#         one-rank data parallelism; about 3 min on an H100), speed (bench
#         model at 5B-I2V shapes vs diffusers, the tiled VAE, a full 50-step
#         predict; about 8 min), training (full-size training steps without
#         and with the flow loss (again in smaller VAE tiles when it does not
#         fit an 80 GB GPU), the flow loss's backward through the VAE by mode
#         and with RAFT large, planning cost; about 10 min); default: all
#         three, in that order.
#   ITEM: one item by name (e.g. planning-cost), to rerun it alone.
#   --dry-run: the same items on the CPU at tiny shapes (the test suite runs
#         it, so the checklist cannot rot between GPU loans); CUDA-only items
#         are reported "skipped: no CUDA device".
#   --budget SECONDS: the whole call's time (a device call's limit, less a
#         margin): each item runs under the smaller of its own limit and
#         the time left, less RESERVE_S for the summary; an item with less
#         than MIN_ITEM_S left is not started ("skipped: not started: ...").
#         So a call cut short still writes its summary, and one call can
#         hold as many items as the time allows (default: no budget).
# Prepared here by scripts/gpu/prepare.sh (gpu-bundle/: a stripped binary and
# the diffusers wheels); on the GPU machine:
#   run(command="OUT=$OUT scripts/gpu/run.sh smoke", carry=["gpu-bundle"])
# Environment: OUT (default gpu-out), BRIDGEV2W (the binary; default
# gpu-bundle/bridgev2w, else target/release/bridgev2w), PYTHON (default the
# project venv's, else python3).
set -uo pipefail
cd "$(dirname "$0")/../.."
ROOT=$PWD
HERE=$ROOT/scripts/gpu
DRY=0
PARTS=()
BUDGET_S=""
RESERVE_S=15   # kept back from --budget for the summary
MIN_ITEM_S=30  # an item with less time than this left is not started
# The items: part, name, time limit (s), needs CUDA, function.
ITEMS="smoke environment 60 0 environment
smoke predict-random-tiny 150 0 predict_random_tiny
smoke predict-demo-model 150 0 predict_demo_model
smoke train-bf16 240 0 train_bf16
smoke distributed-one-rank 150 0 distributed_one_rank
speed bench-model 300 0 bench_model
speed bench-vae-tiled 240 0 bench_vae_tiled
speed predict-full 240 1 predict_full
training train-step-full 300 1 train_step_full
training train-step-flow 300 1 train_step_flow
training train-step-flow-tiles 300 1 train_step_flow_tiles
training bench-flow 300 0 bench_flow
training planning-cost 240 0 planning_cost"
while (($#)); do
    a=$1; shift
    case $a in
        --dry-run) DRY=1 ;;
        --budget)
            BUDGET_S=${1:-}; shift || true
            if ! [[ $BUDGET_S =~ ^[1-9][0-9]*$ ]]; then
                echo "run.sh: --budget ${BUDGET_S:-(missing)}: expected the call's time in whole seconds (e.g. --budget 570 for a 600 s device call)" >&2
                exit 2
            fi
            ;;
        smoke|speed|training) PARTS+=("$a") ;;
        *)
            if grep -q "^[a-z]* $a " <<< "$ITEMS"; then
                PARTS+=("$a")
            else
                echo "run.sh: unknown argument $a (expected --dry-run, a part: smoke, speed, training, or an item: $(cut -d' ' -f2 <<< "$ITEMS" | tr '\n' ' '))" >&2
                exit 2
            fi
            ;;
    esac
done
((${#PARTS[@]})) || PARTS=(smoke speed training)
OUT=${OUT:-$ROOT/gpu-out}
mkdir -p "$OUT/logs" "$OUT/metrics" "$OUT/work"
OUT=$(cd "$OUT" && pwd)
export OUT
WORK=$OUT/work

BIN=${BRIDGEV2W:-}
[[ -z $BIN && -x $ROOT/gpu-bundle/bridgev2w ]] && BIN=$ROOT/gpu-bundle/bridgev2w
[[ -z $BIN ]] && BIN=$ROOT/target/release/bridgev2w
PY=${PYTHON:-}
[[ -z $PY && -x $ROOT/.venv/bin/python ]] && PY=$ROOT/.venv/bin/python
[[ -z $PY ]] && PY=python3
CHECK=("$PY" "$HERE/checklist.py")

# The binary links the Python's libtorch; libtorch_cuda.so is preloaded so
# that a binary built against the CPU wheel registers CUDA (same torch
# version on both sides).
TORCH_LIB=$("$PY" -c 'import os, torch; print(os.path.join(os.path.dirname(torch.__file__), "lib"))')
export LD_LIBRARY_PATH="$TORCH_LIB${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
HAS_CUDA=$("$PY" -c 'import torch; print(int(torch.cuda.is_available()))')
DEVICE=cpu
if [[ $DRY == 0 && $HAS_CUDA == 1 ]]; then
    DEVICE=cuda
    [[ -f $TORCH_LIB/libtorch_cuda.so ]] && export LD_PRELOAD="$TORCH_LIB/libtorch_cuda.so${LD_PRELOAD:+:$LD_PRELOAD}"
fi
# diffusers from the bundle's wheels when the Python lacks it.
if ! "$PY" -c 'import diffusers' 2>/dev/null && compgen -G "$ROOT/gpu-bundle/wheels/*.whl" >/dev/null; then
    "$PY" -m pip install --quiet --no-index --no-deps --target "$WORK/pylib" "$ROOT"/gpu-bundle/wheels/*.whl \
        > "$OUT/logs/pip.log" 2>&1
    export PYTHONPATH="$WORK/pylib${PYTHONPATH:+:$PYTHONPATH}"
fi
# Sizes: the real ones on a GPU, tiny ones in the dry run.
if [[ $DRY == 1 ]]; then
    BIG=random:tiny; BIG_PRECISION=f32; TRAIN_STEPS=3; PLAN_SAMPLES=4
    BENCH=(--style 5b-i2v --layers 1 --frames 1 --height 32 --width 48 --precision f32)
    FLOW=(--vae tiny --frames 9 --height 64 --width 96 --tile 48x40 --precision f32)
    FLOW_RAFT=(--flow raft_small --raft-iterations 2)
else
    BIG=random:cogvideox-5b-i2v; BIG_PRECISION=bf16; TRAIN_STEPS=20; PLAN_SAMPLES=4
    BENCH=(--style 5b-i2v --layers 42 --frames 25 --height 480 --width 720 --precision bf16 --batch 2)
    FLOW=(--vae cogvideox --frames 25 --height 480 --width 720 --tile 240x360 --precision bf16)
    FLOW_RAFT=(--flow raft_large --raft-iterations 12)
fi

# item NAME LIMIT_S NEEDS_CUDA FUNCTION: runs FUNCTION with its output in
# logs/NAME.log and records the status line in items.tsv.
item() {
    local name=$1 limit=$2 needs_cuda=$3 fn=$4 status rc
    local log=$OUT/logs/$name.log start=$SECONDS
    local left="" cut=0
    if [[ -n $BUDGET_S ]]; then
        left=$((BUDGET_S - SECONDS - RESERVE_S))
        ((left < limit)) && { cut=1; limit=$((left > 0 ? left : 0)); }
    fi
    if [[ $needs_cuda == 1 && $DEVICE != cuda ]]; then
        status="skipped: no CUDA device"
    elif ((cut && limit < MIN_ITEM_S)); then
        status="skipped: not started: ${limit}s of the --budget ${BUDGET_S}s left (its limit: ${2}s)"
    else
        echo "== $name (at most ${limit}s)" >&2
        rm -f "$WORK/$name.skip"
        timeout --kill-after=10 "$limit" bash -c "$fn" > "$log" 2>&1
        rc=$?
        case $rc in
            0) status=ok
               # An item whose figures another item's make unneeded says why in NAME.skip.
               [[ -f $WORK/$name.skip ]] && status="skipped: $(head -n 1 "$WORK/$name.skip")" ;;
            124|137) status="failed: over ${limit}s"
                     ((cut)) && status+=" (cut to the --budget ${BUDGET_S}s; its limit: ${2}s)" ;;
            *) status="failed: exit $rc (see logs/$name.log: $(tail -n 1 "$log" | cut -c1-160))" ;;
        esac
    fi
    printf '%s\t%s\t%s\t%s\n' "$name" "$status" "$((SECONDS - start))" "logs/$name.log" >> "$OUT/items.tsv"
    echo "   $name: $status" >&2
}
export BIN PY DEVICE DRY WORK BIG BIG_PRECISION TRAIN_STEPS PLAN_SAMPLES ROOT HERE
export BENCH_ARGS="${BENCH[*]}" FLOW_ARGS="${FLOW[*]}" FLOW_RAFT_ARGS="${FLOW_RAFT[*]}"

# gpu_poll NAME COMMAND...: runs COMMAND while nvidia-smi records the used
# memory, then records the peak as NAME's peak_gpu_memory_mib.
gpu_poll() {
    local name=$1; shift
    local poll=$WORK/$name.mem pid=""
    if [[ $DEVICE == cuda ]] && command -v nvidia-smi >/dev/null; then
        nvidia-smi --query-gpu=memory.used --format=csv,noheader,nounits -lms 200 > "$poll" &
        pid=$!
    fi
    "$@"
    local rc=$?
    [[ -n $pid ]] && kill "$pid" 2>/dev/null
    [[ -n $pid ]] && "$PY" "$HERE/checklist.py" peak-mib "$poll" "$name"
    return $rc
}

now() { date +%s.%N; }
since() { "$PY" -c 'import sys, time; print(round(time.time() - float(sys.argv[1]), 3))' "$1"; }
export -f now since

inputs() { # the demo's camera and actions, and masks at SIZE: inputs DIR FRAMES WIDTH HEIGHT
    local dir=$1
    [[ -f $dir/masks.npy ]] && return 0
    "$BIN" demo --no-predict --frames "$2" --out "$dir.demo" --overwrite &&
    "$BIN" masks --robot franka --camera "$dir.demo/camera.json" --actions "$dir.demo/actions.json" \
        --width "$3" --height "$4" --out "$dir" --overwrite &&
    cp "$dir.demo/overlay.png" "$dir/first.png"
}
export -f inputs

environment() {
    nvidia-smi 2>&1 || true
    "$BIN" --version
    "$PY" "$HERE/checklist.py" environment "$([[ $DRY == 1 ]] && echo dry-run || echo "$DEVICE")" \
        "$(cat "$ROOT/gpu-bundle/commit" 2>/dev/null || git -C "$ROOT" rev-parse HEAD 2>/dev/null || echo unknown)"
}

predict_pair() { # NAME MODEL [WEIGHTS]: the same prediction on DEVICE and on the CPU (from link
    # labels: the shipped model is link-coded; a binary model reads their silhouette)
    local name=$1 model=$2 weights=${3:-}
    inputs "$WORK/in-9" 9 96 64 || return 1
    local extra=(); [[ -n $weights ]] && extra=(--weights "$weights")
    for dev in "$DEVICE" cpu; do
        local t0=$(now)
        "$BIN" predict --model "$model" "${extra[@]}" --image "$WORK/in-9/first.png" --masks "$WORK/in-9/labels.npy" \
            --steps 4 --guidance 1 --seed 0 --device "$dev" --out "$WORK/$name-$dev" --overwrite || return 1
        "$PY" "$HERE/checklist.py" record-seconds "$name" "${dev%%:*}_seconds" "$(since "$t0")"
    done
    "$PY" "$HERE/checklist.py" compare-videos "$WORK/$name-$DEVICE/video.npy" "$WORK/$name-cpu/video.npy" "$name"
}
predict_random_tiny() { predict_pair predict-random-tiny random:tiny; }
predict_demo_model() {
    predict_pair predict-demo-model "$ROOT/assets/demo-model/backbone" "$ROOT/assets/demo-model/bridgev2w.safetensors"
}
export -f predict_pair

dataset() { # DIR FRAMES WIDTH HEIGHT EPISODES
    [[ -f $1/meta/info.json ]] && return 0
    "$BIN" synth --out "$1" --episodes-per-split "$5,0,0,0" --frames "$2" --width "$3" --height "$4" --tasks pick_place
}
export -f dataset

config() { # FILE OUT BACKBONE DATASET DEVICE AUTOCAST CHECKPOINTING STEPS EXTRA
    cat > "$1" <<TOML
[model]
backbone = "$3"
device = "$5"
$9
[data]
dataset = "$4"
[train]
out = "$2"
batch_size = 1
max_steps = $8
warmup_steps = 1
checkpoint_every = 1000
autocast = "$6"
gradient_checkpointing = $7
seed = 0
TOML
}
export -f config

train_bf16() { # bf16 autocast + gradient checkpointing on DEVICE vs f32 on the CPU
    dataset "$WORK/data-9" 9 96 64 2 || return 1
    local tiny='lora_rank = 4
lora_alpha = 4.0'
    config "$WORK/bf16.toml" "$WORK/run-bf16" random:tiny "$WORK/data-9" "$DEVICE" bf16 true "$TRAIN_STEPS" "$tiny"
    config "$WORK/f32.toml" "$WORK/run-f32" random:tiny "$WORK/data-9" cpu "off" false "$TRAIN_STEPS" "$tiny"
    "$BIN" train "$WORK/bf16.toml" --quiet --overwrite || return 1
    "$BIN" train "$WORK/f32.toml" --quiet --overwrite || return 1
    "$PY" "$HERE/checklist.py" compare-losses "$WORK/run-bf16/metrics.jsonl" "$WORK/run-f32/metrics.jsonl" train-bf16
}

distributed_one_rank() { # torchrun with one rank (c10d: NCCL on CUDA, Gloo on the CPU): the same losses as without it
    dataset "$WORK/data-9" 9 96 64 2 || return 1
    local tiny='lora_rank = 4
lora_alpha = 4.0'
    config "$WORK/dp.toml" "$WORK/run-dp" random:tiny "$WORK/data-9" "$DEVICE" off false 5 "$tiny"
    config "$WORK/single.toml" "$WORK/run-single" random:tiny "$WORK/data-9" "$DEVICE" off false 5 "$tiny"
    BRIDGEV2W_DIST_TIMEOUT=120 "$PY" -m torch.distributed.run --standalone --nproc-per-node 1 --no-python \
        "$BIN" train "$WORK/dp.toml" --quiet --overwrite || return 1
    "$BIN" train "$WORK/single.toml" --quiet --overwrite || return 1
    "$PY" "$HERE/checklist.py" compare-losses "$WORK/run-dp/metrics.jsonl" "$WORK/run-single/metrics.jsonl" distributed-one-rank
}

bench_model() { # one CFG denoising step and the VAE, this crate vs diffusers, same run
    gpu_poll bench-model "$BIN" bench model $BENCH_ARGS --device "$DEVICE" --python "$PY" --repo "$ROOT" \
        | tee "$WORK/bench-model.txt" || return 1
    "$PY" "$HERE/checklist.py" bench-table "$WORK/bench-model.txt" bench-model
}

bench_vae_tiled() { # the VAE with spatial tiling (as predict runs it above 256x256), both sides
    # One transformer block: the VAE rows are the point.
    gpu_poll bench-vae-tiled "$BIN" bench model $(sed 's/--layers [0-9]*/--layers 1/' <<< "$BENCH_ARGS") \
        --vae-tiling --device "$DEVICE" \
        --python "$PY" --repo "$ROOT" | tee "$WORK/bench-vae-tiled.txt" || return 1
    "$PY" "$HERE/checklist.py" bench-table "$WORK/bench-vae-tiled.txt" bench-vae-tiled
}
predict_full() { # one 50-step prediction at the full size, random weights
    inputs "$WORK/in-25" 25 720 480 || return 1
    local t0=$(now)
    gpu_poll predict-full "$BIN" predict --model "$BIG" --image "$WORK/in-25/first.png" --masks "$WORK/in-25/masks.npy" \
        --steps 50 --guidance 6 --seed 0 --precision "$BIG_PRECISION" --device "$DEVICE" \
        --out "$WORK/predict-full" --overwrite || return 1
    "$PY" "$HERE/checklist.py" record-seconds predict-full seconds "$(since "$t0")"
}

train_step_full() { # full-size training steps: 8-block ControlNet + LoRA r64, bf16, checkpointing
    dataset "$WORK/data-25" 25 720 480 1 || return 1
    config "$WORK/full.toml" "$WORK/run-full" "$BIG" "$WORK/data-25" "$DEVICE" bf16 true 3 \
        "lora_rank = 64
lora_alpha = 64.0"
    gpu_poll train-step-full "$BIN" train "$WORK/full.toml" --quiet --overwrite || return 1
    "$PY" "$HERE/checklist.py" step-seconds "$WORK/run-full/metrics.jsonl" train-step-full
}

train_step_flow() { # the same with the flow loss on from the first step (e_switch 0):
    # the decode of the predicted frames and the flow pass (the Lucas-Kanade
    # stand-in; RAFT needs weights the GPU machine cannot download)
    dataset "$WORK/data-25" 25 720 480 1 || return 1
    config "$WORK/flow.toml" "$WORK/run-flow" "$BIG" "$WORK/data-25" "$DEVICE" bf16 true 3 \
        "lora_rank = 64
lora_alpha = 64.0"
    echo "e_switch = 0" >> "$WORK/flow.toml"
    gpu_poll train-step-flow "$BIN" train "$WORK/flow.toml" --quiet --overwrite || return 1
    "$PY" "$HERE/checklist.py" step-seconds "$WORK/run-flow/metrics.jsonl" train-step-flow
}
train_step_flow_tiles() { # only when train-step-flow did not fit an 80 GB GPU: the same
    # with the VAE in tiles of 144x200 px (a third of the default's pixels; the
    # flow loss's backward replays one tile at a time), the setting to advise
    if "$PY" "$HERE/checklist.py" fits-80gb train-step-flow > "$WORK/train-step-flow-tiles.skip"; then
        return 0
    fi
    rm -f "$WORK/train-step-flow-tiles.skip"
    dataset "$WORK/data-25" 25 720 480 1 || return 1
    config "$WORK/flow-tiles.toml" "$WORK/run-flow-tiles" "$BIG" "$WORK/data-25" "$DEVICE" bf16 true 3 \
        "lora_rank = 64
lora_alpha = 64.0
vae_tile = \"144x200\""
    echo "e_switch = 0" >> "$WORK/flow-tiles.toml"
    gpu_poll train-step-flow-tiles "$BIN" train "$WORK/flow-tiles.toml" --quiet --overwrite || return 1
    "$PY" "$HERE/checklist.py" step-seconds "$WORK/run-flow-tiles/metrics.jsonl" train-step-flow-tiles
}
bench_flow() { # the flow loss's decode and gradient through the VAE at full size,
    # batch by batch (training without checkpointing) and unit by unit (with
    # it), with the Lucas-Kanade stand-in, then unit by unit with RAFT large
    # (random weights: its cost at full size): one process each, so that
    # each peak starts from an empty CUDA caching allocator
    for run in "recorded recorded" "stepwise stepwise" "stepwise stepwise_raft"; do
        set -- $run
        local extra=""
        [[ $2 == *_raft ]] && extra=$FLOW_RAFT_ARGS
        "$BIN" bench flow $FLOW_ARGS $extra --device "$DEVICE" --modes "$1" \
            | tee "$WORK/bench-flow-$2.txt" || return 1
        "$PY" "$HERE/checklist.py" flow-row "$WORK/bench-flow-$2.txt" bench-flow "$1" "$2" || return 1
    done
}
planning_cost() { # the cost of CEM's batched candidate predictions: one CEM iteration
    # of S candidates at 4 and at 20 denoising steps (seconds per planned action
    # at S 64 / T 3 scale with the candidates and the steps; the model load is in)
    for pair in "$PLAN_SAMPLES 4" "2 20"; do
        set -- $pair
        local t0=$(now)
        "$BIN" plan --task reach --trials 1 --model "$([[ $DRY == 1 ]] && echo random || echo "$BIG")" \
            --device "$DEVICE" --precision "$BIG_PRECISION" --max-batch 2 --samples "$1" --elites 1 --iters 1 --horizon 1 --max-steps 1 \
            --denoise-steps "$2" --waypoints 0 || return 1
        "$PY" "$HERE/checklist.py" record-seconds planning-cost "seconds_${1}_candidates_${2}_steps" "$(since "$t0")"
    done
}
export -f environment predict_random_tiny predict_demo_model train_bf16 distributed_one_rank \
    bench_model bench_vae_tiled predict_full train_step_full train_step_flow train_step_flow_tiles bench_flow \
    planning_cost gpu_poll

# Each part's items in order, or a single item by name, in the order given.
for part in "${PARTS[@]}"; do
    while read -r p name limit needs_cuda fn; do
        [[ $p == "$part" || $name == "$part" ]] && item "$name" "$limit" "$needs_cuda" "$fn" < /dev/null
    done <<< "$ITEMS"
done
"${CHECK[@]}" summary "$OUT" > /dev/null
echo "run.sh: $OUT/summary.md" >&2
