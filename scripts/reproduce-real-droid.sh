#!/usr/bin/env bash
# BridgeV2W on real robot video: DROID episodes of one rig (the Ctrl-World
# authors' `droid_new_setup*`, a Franka with a Robotiq 2F-85 and two fixed
# ZED 2 exterior cameras), end to end:
#
#   1. calibrate-ext1, calibrate-ext2: each exterior camera calibrated from
#      the robot's own motion (`bridgev2w calibrate`) on CALIB_FIT training
#      episodes, checked on the held-out ones; the focal length is the ZED 2's
#      nominal one (FOCAL_PX at the videos' 320 px width), the pose is fitted;
#   2. data: `bridgev2w convert --format ctrl-world`: the rig's episodes (repeats
#      listed once) at 96x64 with masks and link labels rendered from the
#      calibrated cameras and the recorded joints (robot franka-robotiq); split
#      by episode: TEST episodes never seen in training are `test` (exterior
#      camera 1, the trained view) and `unseen_camera` (exterior camera 2, a
#      view no training episode shows); the others `train` (camera 1 only);
#   3. BridgeV2W fine-tuned on it from the synthetic world's action-free prior
#      (`assets/demo-model/backbone`, fresh ControlNet + LoRA), and the
#      `mask_action = false` ablation from the same prior;
#   4. from scratch: a VAE, an action-free prior and BridgeV2W trained on the
#      real frames alone (stages scratch-vae-image, scratch-vae,
#      scratch-prior, bridgev2w-scratch);
#   5. eval-run of each on test and unseen_camera (PSNR, SSIM, dynamic-region
#      PSNR, Mask-IoU, copying the first frame), side-by-side GIFs, and the
#      section `real-video` of docs/results.md (eval-report --section).
#
# Usage: scripts/reproduce-real-droid.sh [OUT_DIR]      (default runs/real-droid)
# Environment: DROID (default ../shared/realdata/droid: the Ctrl-World layout),
#   FT_STEPS SCRATCH_VAE_IMAGE_STEPS SCRATCH_VAE_STEPS SCRATCH_PRIOR_STEPS
#   SCRATCH=0 (skip step 4) EVAL_VIDEOS EVAL_STEPS KEEP_STATIC RESULTS FOCAL_PX
#   BRIDGEV2W (a built binary; default: build target/release/bridgev2w).
# Rerunning resumes: a finished stage is kept, a cut one resumes from its last
# checkpoint; a stage whose inputs changed is moved aside and redone
# (scripts/lib/stages.sh, as scripts/reproduce-synthetic.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
OUT=${1:-runs/real-droid}
DROID=${DROID:-$ROOT/../shared/realdata/droid}
FT_STEPS=${FT_STEPS:-2000}
SCRATCH=${SCRATCH:-1}
SCRATCH_VAE_IMAGE_STEPS=${SCRATCH_VAE_IMAGE_STEPS:-2500}
SCRATCH_VAE_STEPS=${SCRATCH_VAE_STEPS:-300}
SCRATCH_PRIOR_STEPS=${SCRATCH_PRIOR_STEPS:-3000}
EVAL_VIDEOS=${EVAL_VIDEOS:-8}
EVAL_STEPS=${EVAL_STEPS:-2}
# As the synthetic study: outside the region the masks have swept (dilated by
# KEEP_STATIC px) a predicted frame is the first frame; the row "every pixel
# generated" scores BridgeV2W without it. Empty: off.
KEEP_STATIC=${KEEP_STATIC-0}
RESULTS=${RESULTS:-docs/results.md}
# The ZED 2's left camera at 1280x720 has fx about 532 px (StereoLabs'
# per-unit calibration files, a few per cent apart): 133 at the 320 px wide
# videos, whose 180 rows were stretched to 192 (fy/fx 192/180).
FOCAL_PX=${FOCAL_PX:-133}
FY_OVER_FX=1.0667
PRIOR=${PRIOR:-$ROOT/assets/demo-model/backbone}

[[ -d $DROID ]] || { echo "error: DROID=$DROID is not a folder (the Ctrl-World layout of ../shared/realdata/droid)" >&2; exit 1; }
[[ -d $PRIOR ]] || { echo "error: PRIOR=$PRIOR is not a model folder (assets/demo-model/backbone)" >&2; exit 1; }
DROID=$(cd "$DROID" && pwd)

DATA_STAGE=data
# shellcheck source=scripts/lib/stages.sh
source "$ROOT/scripts/lib/stages.sh"
setup_run

# The split, by episode (names relative to DROID; repeats of these under
# other names are listed by convert and not converted). Held out: one or two
# episodes of every task of the rig.
TEST=(
    droid_new_setup/val/0002 droid_new_setup/val/0005 droid_new_setup/val/0007
    droid_new_setup/val/0009 droid_new_setup/val/0011 droid_new_setup/val/0013
    droid_new_setup_full/drawer/val/0004 droid_new_setup_full/pickplace/val/0008
)
# The calibration's fit episodes, all training episodes (three tasks).
CALIB_FIT=(
    droid_new_setup_full/drawer/val/0000 droid_new_setup_full/laptop/val/0002
    droid_new_setup_full/pickplace/val/0004
)

episode_files() { # episode_files NAME CAMERA: --video/--joints pair of the Ctrl-World layout
    local name=$1 cam=$2 coll split id
    id=${name##*/}
    split=${name%/*}
    split=${split##*/}
    coll=${name%/"$split"/"$id"}
    printf '%s\n' "$DROID/$coll/videos/$split/$id/$cam.mp4" "$DROID/$coll/annotation/$split/$id.json"
}

calibrate_camera() { # calibrate_camera ROLE INDEX
    local role=$1 cam=$2 name args=() f
    for name in "${CALIB_FIT[@]}"; do
        mapfile -t f < <(episode_files "$name" "$cam")
        args+=(--video "${f[0]}" --joints "${f[1]}")
    done
    for name in "${TEST[@]}"; do
        mapfile -t f < <(episode_files "$name" "$cam")
        args+=(--check-video "${f[0]}" --check-joints "${f[1]}")
    done
    args+=(--robot franka-robotiq --focal-px "$FOCAL_PX" --fy-over-fx "$FY_OVER_FX" --analysis-width 160)
    fresh "calibrate-$role" "$(fingerprint "calibrate ${args[*]}")"
    if [[ -f $OUT/calibrate-$role/camera.json ]]; then
        echo "== calibrate-$role: done before from the same inputs, kept"
        return
    fi
    rm -rf "$OUT/calibrate-$role"
    stage "calibrate-$role" "$BIN" calibrate "${args[@]}" --out "$OUT/calibrate-$role"
}
calibrate_camera ext1 0
calibrate_camera ext2 1

# Every episode of the rig (its collections under DROID).
mapfile -t RIG < <(cd "$DROID" && find droid_new_setup* -path '*/annotation/*/*.json' | sort |
    sed -E 's#^(.*)/annotation/([^/]+)/([^/]+)\.json$#\1/\2/\3#')
[[ ${#RIG[@]} -gt 0 ]] || { echo "error: no droid_new_setup* episodes under $DROID" >&2; exit 1; }
CONVERT_ARGS=(--format ctrl-world "$DROID" --width 96 --height 64 --split train
    --camera "ext1=$OUT/calibrate-ext1/camera.json" --camera "ext2=$OUT/calibrate-ext2/camera.json"
    --include "$(IFS=,; echo "${RIG[*]}")")
for name in "${TEST[@]}"; do
    CONVERT_ARGS+=(--split-rule "$name:ext1=test" --split-rule "$name:ext2=unseen_camera")
done
CONVERT_ARGS+=(--split-rule "*:ext2=-")
fresh data "$(fingerprint "convert ${CONVERT_ARGS[*]}" "$OUT/calibrate-ext1.inputs" "$OUT/calibrate-ext2.inputs")"
if [[ ! -f $OUT/data/meta/info.json ]]; then
    rm -rf "$OUT/data"
    stage data "$BIN" convert "${CONVERT_ARGS[@]}" --out "$OUT/data"
fi

data_section() { # clips of 9 frames (1.8 s at 5 Hz) at 96x64, ARG1 frames (default 9)
    cat <<EOF
[data]
dataset = "$OUT/data"
frames = ${1:-9}
width = 96
height = 64
clips_per_video = 4
EOF
}
finetune_config() { # finetune_config OUT MASK_ACTION BACKBONE
    local coding=""
    [[ $2 == true ]] && coding='mask_coding = "links"'
    finetune_toml "$3" "$coding" every_frame "$1" "$2"
}
finetune_config "$OUT/bridgev2w" true "$PRIOR" >"$OUT/configs/bridgev2w.toml"
finetune_config "$OUT/ablation-action-mlp" false "$PRIOR" >"$OUT/configs/ablation-action-mlp.toml"
finetune_config "$OUT/bridgev2w-scratch" true "$OUT/scratch-prior/final/backbone" >"$OUT/configs/bridgev2w-scratch.toml"
# The from-scratch backbone: the synthetic study's stages and settings on the
# real frames (scripts/reproduce-synthetic.sh: small2x VAE, a 256-wide
# transformer), without its decoder-only stage.
cat >"$OUT/configs/scratch-vae-image.toml" <<EOF
[model]
backbone = "random:small2x"
lora_rank = 0
$(data_section 1)
[train]
stage = "vae"
out = "$OUT/scratch-vae-image"
batch_size = 16
max_steps = $SCRATCH_VAE_IMAGE_STEPS
lr = 1e-3
warmup_steps = 20
checkpoint_every = 250
color_augment = true
EOF
cat >"$OUT/configs/scratch-vae.toml" <<EOF
[model]
backbone = "$OUT/scratch-vae-image/final/backbone"
lora_rank = 0
$(data_section)
[train]
stage = "vae"
out = "$OUT/scratch-vae"
batch_size = 4
max_steps = $SCRATCH_VAE_STEPS
lr = 5e-4
warmup_steps = 20
checkpoint_every = 100
color_augment = true
inflate_image_vae = true
EOF
cat >"$OUT/configs/scratch-prior.toml" <<EOF
[model]
backbone = "$OUT/scratch-vae/final/backbone"
transformer = "small2x-wide"
lora_rank = 0
image_conditioning = "every_frame"
$(data_section)
[train]
stage = "prior"
out = "$OUT/scratch-prior"
batch_size = 4
max_steps = $SCRATCH_PRIOR_STEPS
lr = 5e-4
warmup_steps = 100
checkpoint_every = 500
EOF

KEEP_ARGS=()
[[ -n $KEEP_STATIC ]] && KEEP_ARGS=(--keep-static "$KEEP_STATIC")
evaluate() { # evaluate NAME JSON_NAME [SAMPLING...]: eval-run of OUT/NAME into OUT/eval-JSON_NAME.json, kept when unchanged
    local name=$1 json=$2 fp
    shift 2
    fp=$(fingerprint "eval $name --max-videos $EVAL_VIDEOS --steps $EVAL_STEPS $*" "$OUT/$name.inputs")
    if [[ -f $OUT/eval-$json.json && $(cat "$OUT/eval-$json.inputs" 2>/dev/null) == "$fp" ]]; then
        echo "== eval $json: done before from the same run and settings, kept"
        return
    fi
    rm -f "$OUT/eval-$json.json" "$OUT/eval-$json.inputs"
    stage "eval $json" "$BIN" eval-run "$OUT/configs/$name.toml" --run "$OUT/$name" \
        --splits test,unseen_camera --max-videos "$EVAL_VIDEOS" --steps "$EVAL_STEPS" "$@" \
        --json "$OUT/eval-$json.json"
    printf '%s\n' "$fp" >"$OUT/eval-$json.inputs"
}
train bridgev2w
evaluate bridgev2w bridgev2w "${KEEP_ARGS[@]}"
[[ -n $KEEP_STATIC ]] && evaluate bridgev2w bridgev2w-generated
train ablation-action-mlp
evaluate ablation-action-mlp ablation-action-mlp "${KEEP_ARGS[@]}"
ENTRIES=(--entry "BridgeV2W from the synthetic prior=$OUT/eval-bridgev2w.json")
[[ -n $KEEP_STATIC ]] && ENTRIES+=(--entry "BridgeV2W, every pixel generated=$OUT/eval-bridgev2w-generated.json")
ENTRIES+=(--entry "Ablation: actions through an MLP=$OUT/eval-ablation-action-mlp.json")
RUNS=(--training-run "bridgev2w=$OUT/bridgev2w" --training-run "ablation-action-mlp=$OUT/ablation-action-mlp")
if [[ $SCRATCH == 1 ]]; then
    train scratch-vae-image
    train scratch-vae scratch-vae-image
    train scratch-prior scratch-vae
    train bridgev2w-scratch scratch-prior
    evaluate bridgev2w-scratch bridgev2w-scratch "${KEEP_ARGS[@]}"
    ENTRIES+=(--entry "BridgeV2W from scratch (real frames only)=$OUT/eval-bridgev2w-scratch.json")
    RUNS+=(--training-run "scratch-vae-image=$OUT/scratch-vae-image" --training-run "scratch-prior=$OUT/scratch-prior"
        --training-run "bridgev2w-scratch=$OUT/bridgev2w-scratch")
fi

GRIDS="${RESULTS%.md}/grids-real"
COMPARE=(--compare "$OUT/configs/ablation-action-mlp.toml" "$OUT/ablation-action-mlp")
GRID_RUNS=("$OUT/bridgev2w.inputs" "$OUT/ablation-action-mlp.inputs")
if [[ $SCRATCH == 1 ]]; then
    COMPARE+=(--compare "$OUT/configs/bridgev2w-scratch.toml" "$OUT/bridgev2w-scratch")
    GRID_RUNS+=("$OUT/bridgev2w-scratch.inputs")
fi
fp=$(fingerprint "grid --out $GRIDS --steps $EVAL_STEPS ${KEEP_ARGS[*]}" "${GRID_RUNS[@]}")
if [[ ! -f $GRIDS/test.gif || ! -f $GRIDS/unseen_camera.gif || $(cat "$OUT/grids.inputs" 2>/dev/null) != "$fp" ]]; then
    rm -f "$OUT/grids.inputs"
    stage grids "$BIN" eval-grid "$OUT/configs/bridgev2w.toml" --run "$OUT/bridgev2w" \
        "${COMPARE[@]}" --splits test,unseen_camera --out "$GRIDS" --overwrite --clips 4 --steps "$EVAL_STEPS" "${KEEP_ARGS[@]}"
    printf '%s\n' "$fp" >"$OUT/grids.inputs"
fi

iou() { # iou ROLE: the calibration's held-out IoU on the test episodes
    python3 -c 'import json,sys; print("%.3f" % json.load(open(sys.argv[1]))["checked_episodes_mean_iou"])' "$OUT/calibrate-$1/residuals.json"
}
PRE="$OUT/preamble.md"
{
    echo "Produced by \`scripts/reproduce-real-droid.sh\` on $(nproc) CPU core(s) ($(date -u +%Y-%m-%d))."
    repeats=$(python3 -c 'import json,sys; print(len(json.load(open(sys.argv[1]))["skipped"]))' "$OUT/data/skipped.json")
    echo "Data: the ${#RIG[@]} DROID episodes of the Ctrl-World authors' rig (\`droid_new_setup*\` of \`../shared/realdata/droid\`, CC BY 4.0), $((${#RIG[@]} - repeats)) distinct ($repeats repeat another's joint recording under another name and are converted once: \`$OUT/data/skipped.json\`); real video at 5 Hz, 320x192 resized to 96x64; clips of 9 frames (1.8 s)."
    echo "Split by episode: ${#TEST[@]} held-out episodes (\`${TEST[*]}\`) are *In-Domain* (exterior camera 1, the view trained on) and *Unseen Camera Viewpoint* (exterior camera 2, which no training episode shows); the others are the training split (camera 1 only)."
    echo "Masks and link labels: rendered from the recorded joints through the cameras calibrated from the robot's own motion (\`bridgev2w calibrate\`, robot \`franka-robotiq\`: Franka + Robotiq 2F-85 as DROID's; focal length fixed at the ZED 2's nominal $FOCAL_PX px, pose fitted on ${#CALIB_FIT[@]} training episodes): held-out-episode IoU of the rendered robot against the robot pixels found in the video $(iou ext1) (camera 1), $(iou ext2) (camera 2). They are not ground truth: Mask-IoU below is against these masks."
    echo "Models: BridgeV2W (ControlNet of 2 blocks + LoRA rank 64, link-coded masks) and the \`mask_action = false\` ablation fine-tuned $FT_STEPS steps each (batch 4) from the synthetic world's action-free prior (\`assets/demo-model/backbone\`: VAE and transformer trained on the synthetic world only)$([[ $SCRATCH == 1 ]] && echo "; *from scratch*: a small2x VAE ($SCRATCH_VAE_IMAGE_STEPS steps on single frames, $SCRATCH_VAE_STEPS on clips) and an action-free prior ($SCRATCH_PRIOR_STEPS steps) trained on the training split's real frames, then BridgeV2W $FT_STEPS steps")."
    echo "Each method is scored on the first clip of the first $EVAL_VIDEOS episodes of each split, $EVAL_STEPS denoising steps."
    if [[ -n $KEEP_STATIC ]]; then
        echo "Predictions keep the static scene (\`--keep-static $KEEP_STATIC\`) as in the synthetic study; the row *every pixel generated* is BridgeV2W without it."
    fi
    echo
    echo "Wall time of the run that finished each stage: a stage resumed after a cut counts from its resume, and the machine's other work at the time is in it."
    echo
    echo "| stage | wall time (s) |"
    echo "|---|---|"
    awk -F'\t' '{printf "| %s | %s |\n", $1, $2}' "$LOG"
} >"$PRE"
"$BIN" eval-report --section real-video --title "Video prediction on real DROID video" \
    --preamble "$PRE" --out "$RESULTS" "${ENTRIES[@]}" "${RUNS[@]}" --grids "$GRIDS"
echo "== done: $RESULTS (section real-video)"
