#!/usr/bin/env bash
# The CPU proof of BridgeV2W in the synthetic tabletop world, end to end:
#
#   1. synthetic dataset (train / test / unseen_camera / unseen_scene),
#   2. the "pretrained video prior": a small causal VAE (stage vae), then an
#      action-free image-to-video transformer on its latents (stage prior),
#   3. BridgeV2W fine-tuning from the prior: ControlNet on embodiment masks +
#      LoRA, diffusion + dynamics + flow losses,
#   4. the mask_action = false ablation (end-effector actions through an MLP)
#      with the same budget,
#   5. eval-run of both on test / unseen_camera / unseen_scene (PSNR, SSIM,
#      Mask-IoU, copy-the-first-frame baseline),
#   6. eval-report: the table in docs/results.md (section `video`).
#
# Usage: scripts/reproduce-synthetic.sh [OUT_DIR]      (default runs/reproduce)
# Budgets (environment, defaults sized for ~2 h on a 2-core CPU):
#   VAE_STEPS PRIOR_STEPS FT_STEPS EVAL_VIDEOS EVAL_STEPS RESULTS
# EXPORT_DEMO=1 also copies the fine-tuned model to assets/demo-model (the
# default model of `bridgev2w demo`).
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
OUT=${1:-runs/reproduce}
VAE_STEPS=${VAE_STEPS:-1200}
PRIOR_STEPS=${PRIOR_STEPS:-1500}
FT_STEPS=${FT_STEPS:-1000}
EVAL_VIDEOS=${EVAL_VIDEOS:-12}
EVAL_STEPS=${EVAL_STEPS:-20}
RESULTS=${RESULTS:-docs/results.md}
EPISODES=${EPISODES:-160,12,12,12}

BIN=${BRIDGEV2W:-$ROOT/target/release/bridgev2w}
if [[ -z ${BRIDGEV2W:-} ]]; then
    echo "== building bridgev2w (release)"
    scripts/setup-venv.sh
    cargo build --release -p bridgev2w-cli
fi
[[ -x $BIN ]] || { echo "error: $BIN is not an executable (set BRIDGEV2W)" >&2; exit 1; }

mkdir -p "$OUT/configs"
LOG="$OUT/timings.tsv"
: >"$LOG"
stage() { # stage NAME COMMAND...: runs it, records its wall time
    local name=$1 t0
    shift
    echo "== $name: $*"
    t0=$(date +%s)
    "$@"
    printf '%s\t%s\n' "$name" "$(($(date +%s) - t0))" >>"$LOG"
}

# Shared data section: 9-frame clips at 96x64 from 17-frame episodes.
data_section() {
    cat <<EOF
[data]
dataset = "$OUT/synth"
frames = 9
width = 96
height = 64
clips_per_video = 2
EOF
}

cat >"$OUT/configs/vae.toml" <<EOF
[model]
backbone = "random:small"
lora_rank = 0
$(data_section)
[train]
stage = "vae"
out = "$OUT/vae"
batch_size = 4
max_steps = $VAE_STEPS
lr = 1e-3
warmup_steps = 20
checkpoint_every = 200
EOF

cat >"$OUT/configs/prior.toml" <<EOF
[model]
backbone = "$OUT/vae/final/backbone"
lora_rank = 0
$(data_section)
[train]
stage = "prior"
out = "$OUT/prior"
batch_size = 4
max_steps = $PRIOR_STEPS
lr = 5e-4
warmup_steps = 100
checkpoint_every = 500
EOF

finetune_config() { # finetune_config OUT MASK_ACTION
    cat <<EOF
[model]
backbone = "$OUT/prior/final/backbone"
lora_rank = 64
lora_alpha = 64
controlnet_layers = 2
action_hidden = 128
$(data_section)
[train]
out = "$1"
batch_size = 4
max_steps = $FT_STEPS
lr = 5e-4
warmup_steps = 100
e_switch = 5
checkpoint_every = 250
[ablation]
mask_action = $2
EOF
}
finetune_config "$OUT/bridgev2w" true >"$OUT/configs/bridgev2w.toml"
finetune_config "$OUT/ablation-action-mlp" false >"$OUT/configs/ablation-action-mlp.toml"

if [[ ! -d $OUT/synth ]]; then
    stage synth "$BIN" synth --out "$OUT/synth" --episodes-per-split "$EPISODES" --frames 17
fi
train() { # train NAME: trains unless OUT/NAME/final exists; resumes a cut run
    local name=$1 resume=()
    if [[ -f $OUT/$name/final/weights.safetensors ]]; then
        echo "== $name: done before, kept"
        return
    fi
    [[ -d $OUT/$name/checkpoints ]] && resume=(--resume "$OUT/$name")
    stage "$name" "$BIN" train "$OUT/configs/$name.toml" --quiet "${resume[@]}"
}
train vae
train prior
train bridgev2w
train ablation-action-mlp

for name in bridgev2w ablation-action-mlp; do
    stage "eval $name" "$BIN" eval-run "$OUT/configs/$name.toml" --run "$OUT/$name" \
        --max-videos "$EVAL_VIDEOS" --steps "$EVAL_STEPS" --json "$OUT/eval-$name.json"
done

PRE="$OUT/preamble.md"
{
    echo "Produced by \`scripts/reproduce-synthetic.sh\` on $(nproc) CPU core(s) ($(date -u +%Y-%m-%d))."
    echo "Dataset: \`bridgev2w synth\`, Franka, 96x64, episodes of 17 frames ($EPISODES train/test/unseen_camera/unseen_scene); clips of 9 frames."
    echo "Models: \`random:small\` VAE (3 blocks, 16 latent channels, 4x space / 4x time) trained $VAE_STEPS steps (L1 + KL);"
    echo "action-free I2V prior (4 layers, 4 heads x 32) trained $PRIOR_STEPS steps; BridgeV2W (ControlNet of 2 blocks + LoRA rank 64)"
    echo "and the \`mask_action = false\` ablation (end-effector actions through an MLP, LoRA rank 64) fine-tuned $FT_STEPS steps each from the prior,"
    echo "batch 4, diffusion + dynamics (K = 4, 0.1) + flow (0.05 after 5 epochs; flow estimator: the differentiable Lucas-Kanade stand-in, no RAFT weights here)."
    echo "Each method is scored on the first clip of the first $EVAL_VIDEOS episodes of each split."
    echo
    echo "| stage | wall time (s) |"
    echo "|---|---|"
    awk -F'\t' '{printf "| %s | %s |\n", $1, $2}' "$LOG"
} >"$PRE"
"$BIN" eval-report --preamble "$PRE" --out "$RESULTS" \
    --entry "BridgeV2W (masks, ControlNet)=$OUT/eval-bridgev2w.json" \
    --entry "Ablation: actions through an MLP=$OUT/eval-ablation-action-mlp.json"

if [[ ${EXPORT_DEMO:-0} == 1 ]]; then
    rm -rf assets/demo-model.tmp
    mkdir -p assets/demo-model.tmp
    cp -r "$OUT/prior/final/backbone" assets/demo-model.tmp/backbone
    cp "$OUT/bridgev2w/final/weights.safetensors" assets/demo-model.tmp/bridgev2w.safetensors
    cp "$OUT/configs/bridgev2w.toml" assets/demo-model.tmp/train-config.toml
    rm -rf assets/demo-model && mv assets/demo-model.tmp assets/demo-model
    du -sh assets/demo-model
fi
echo "== done: $RESULTS"
