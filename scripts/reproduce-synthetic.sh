#!/usr/bin/env bash
# The CPU proof of BridgeV2W in the synthetic tabletop world, end to end:
#
#   1. synthetic dataset (train / test / unseen_camera / unseen_scene): the
#      scripted tasks and random "play" episodes (TASKS),
#   2. the "pretrained video prior": a small causal VAE, trained first on
#      single frames (stage vae-image: the causal VAE encodes the first frame
#      alone, and single frames are cheap), then on clips (stage vae); then
#      an action-free image-to-video transformer on its latents (stage prior);
#      then the VAE's decoder alone trained further on clips, its encoder and
#      so the prior's latents unchanged (stage vae-decoder: its backbone, the
#      prior's transformer with the better decoder, is the one every model is
#      evaluated and shipped with),
#   3. BridgeV2W fine-tuning from the prior: ControlNet on embodiment masks +
#      LoRA, diffusion + dynamics + flow losses,
#   4. the mask_action = false ablation (end-effector actions through an MLP)
#      with the same budget; then the planning model (stage bridgev2w-short):
#      BridgeV2W continued on 3-frame clips, the clip one planned action of 2
#      frames needs (`plan --clip-frames 3`, about a third of a 9-frame
#      prediction's cost),
#   5. eval-run of both on test / unseen_camera / unseen_scene (PSNR, SSIM,
#      Mask-IoU, copy-the-first-frame baseline, PSNR per predicted frame),
#   6. eval-grid: side-by-side GIFs per split (first frame | masks |
#      BridgeV2W | ablation | ground truth) in docs/results/grids/,
#   7. eval-report: the table in docs/results.md (section `video`), with its
#      figures in docs/results/figures/ (the loss curves of every stage,
#      PSNR per predicted frame) and links to the GIFs.
#
# Usage: scripts/reproduce-synthetic.sh [OUT_DIR]      (default runs/reproduce)
# Budgets (environment, defaults sized for ~2.8 h on a 2-core CPU):
#   VAE_IMAGE_STEPS VAE_STEPS PRIOR_STEPS DECODER_STEPS FT_STEPS SHORT_STEPS EVAL_VIDEOS
#   EVAL_STEPS RESULTS
#   EPISODES TASKS PRESET IMAGE_CONDITIONING MASK_CODING
# ENGINE=mujoco simulates and renders the dataset in MuJoCo (`synth --engine
# mujoco`, the MuJoCo venv of scripts/setup-mujoco-venv.sh) instead of the
# built-in world; its results go to the `video-mujoco` section of RESULTS and
# its GIFs to RESULTS_without_.md/grids-mujoco/ (run it with another OUT_DIR,
# e.g. runs/reproduce-mujoco).
# PLAN_TRIALS (default 0, with ENGINE=mujoco 20) adds the planning stages:
# `plan-report` with the perfect model, then with this run's model (exported
# to OUT/model, planning with its bridgev2w-short weights), planning reach,
# push and pick_place PLAN_TRIALS times each against random actions, and
# evaluating the scripted policies PLAN_EVAL_TRIALS (default 10) times each,
# executed in ENGINE's world: sections planning-ENGINE and
# planning-ENGINE-trained of RESULTS (builtin: planning-builtin...).
# Rerunning resumes: a finished stage is kept, a cut one resumes from its last
# checkpoint. Each stage records a fingerprint of its inputs (its config and
# the fingerprints of the stages it starts from) in OUT/NAME.inputs; a stage
# whose inputs changed is moved aside to OUT/NAME.stale-FINGERPRINT and redone;
# a training stage whose only change is a larger step budget continues from
# its checkpoints (exactly the longer run).
# EXPORT_DEMO=1 also copies the fine-tuned model to assets/demo-model (the
# default model of `bridgev2w demo`).
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
OUT=${1:-runs/reproduce}
VAE_IMAGE_STEPS=${VAE_IMAGE_STEPS:-2500}
VAE_STEPS=${VAE_STEPS:-300}
PRIOR_STEPS=${PRIOR_STEPS:-3000}
# The decoder-only stage (session 30: 400 steps lifted the reconstruction
# ceiling from 36.37 / 36.04 / 33.85 to 36.85 / 36.62 / 35.32 dB on
# test / unseen_camera / unseen_scene; docs/results.md, section levers).
DECODER_STEPS=${DECODER_STEPS:-400}
FT_STEPS=${FT_STEPS:-2000}
# The planning model's steps on 3-frame clips (session 38: 400 steps from the
# shipped weights planned reach 12 of 20 on the train split with 3-frame
# clips, against 7 for the model trained on 9-frame clips alone;
# docs/results.md, section levers).
SHORT_STEPS=${SHORT_STEPS:-400}
EVAL_VIDEOS=${EVAL_VIDEOS:-12}
# Denoising steps of the evaluation: 2, chosen on the training split (the
# first clip of 12 training episodes, 256-wide model, session 20: PSNR
# 26.24 / 25.95 / 25.03 / 24.35 dB and SSIM 0.864 / 0.870 / 0.852 / 0.835
# at 1 / 2 / 5 / 20 steps; fewer steps give the model's mean prediction
# instead of a grainy sample). The tables until session 20 used 20.
EVAL_STEPS=${EVAL_STEPS:-2}
# The evaluation keeps the static scene (`--keep-static MARGIN_PX`, beyond the
# paper): outside the region the robot's masks have swept so far (dilated by
# KEEP_STATIC pixels) each predicted frame is the first frame; the BridgeV2W
# row without it (every pixel generated) is scored too. Empty: off.
# 0 chosen on the wide model (session 24: margins 0 / 2 / 4 px gave PSNR
# 25.76 / 25.58 / 25.51 dB, SSIM 0.912 / 0.903 / 0.898 in-domain).
KEEP_STATIC=${KEEP_STATIC-0}
KEEP_ARGS=()
[[ -n $KEEP_STATIC ]] && KEEP_ARGS=(--keep-static "$KEEP_STATIC")
RESULTS=${RESULTS:-docs/results.md}
EPISODES=${EPISODES:-240,12,12,12}
TASKS=${TASKS:-reach,push,pick_place,play,play,play}
# The VAE/transformer presets: small2x (2x space, no time compression,
# patches of 4, a transformer 128 wide), small2x-wide (the same, 256 wide)
# or small (4x space and time, patches of 2). small2x-wide is the default
# since session 28 (the link-coded wide model, docs/results.md).
PRESET=${PRESET:-small2x-wide}
# The autoencoder stages depend only on the VAE, which small2x and
# small2x-wide share: their runs are shared (a small2x-wide prior takes a
# fresh transformer of its preset, model.transformer; the others keep the
# backbone's own).
VAE_PRESET=${PRESET%-wide}
PRIOR_TRANSFORMER=""
[[ $PRESET != "$VAE_PRESET" ]] && PRIOR_TRANSFORMER="transformer = \"$PRESET\""$'\n'
# Without time compression the clip stage starts from the image autoencoder
# applied frame by frame (its temporal taps summed into the current frame's).
INFLATE=false
[[ $PRESET == small2x* ]] && INFLATE=true
# Where the prior and the fine-tuned models take the first frame's latent:
# every_frame (repeated in every latent frame's conditioning channels, so that
# copying the static scene is local; a measured deviation from CogVideoX) or
# first_frame (CogVideoX-I2V: latent frame 0, the rest zero).
IMAGE_CONDITIONING=${IMAGE_CONDITIONING:-every_frame}
# How BridgeV2W's masks fill the mask branch's three channels: binary (the
# paper's silhouette) or links (link-coded from the dataset's labels/, beyond
# the paper). Only a non-binary coding is written into the config, so runs
# made before this setting keep their fingerprints. links is the default
# since session 28 (+2.3 to +2.9 dB over binary masks, docs/results.md).
MASK_CODING=${MASK_CODING:-links}
ENGINE=${ENGINE:-builtin}
case $ENGINE in
builtin | mujoco) ;;
*) echo "error: ENGINE=$ENGINE: expected builtin or mujoco" >&2; exit 1 ;;
esac
case $MASK_CODING in
binary | links) ;;
*) echo "error: MASK_CODING=$MASK_CODING: expected binary or links" >&2; exit 1 ;;
esac

DATA_STAGE=synth
# shellcheck source=scripts/lib/stages.sh
source "$ROOT/scripts/lib/stages.sh"
setup_run

# Shared data section: clips of ARG1 (default 9) frames at 96x64 from
# 17-frame episodes.
data_section() {
    cat <<EOF
[data]
dataset = "$OUT/synth"
frames = ${1:-9}
width = 96
height = 64
clips_per_video = 2
EOF
}

cat >"$OUT/configs/vae-image.toml" <<EOF
[model]
backbone = "random:$VAE_PRESET"
lora_rank = 0
$(data_section 1)
[train]
stage = "vae"
out = "$OUT/vae-image"
batch_size = 16
max_steps = $VAE_IMAGE_STEPS
lr = 1e-3
warmup_steps = 20
checkpoint_every = 250
color_augment = true
EOF

cat >"$OUT/configs/vae.toml" <<EOF
[model]
backbone = "$OUT/vae-image/final/backbone"
lora_rank = 0
$(data_section)
[train]
stage = "vae"
out = "$OUT/vae"
batch_size = 4
max_steps = $VAE_STEPS
lr = 5e-4
warmup_steps = 20
checkpoint_every = 100
color_augment = true
inflate_image_vae = $INFLATE
EOF

cat >"$OUT/configs/prior.toml" <<EOF
[model]
backbone = "$OUT/vae/final/backbone"
${PRIOR_TRANSFORMER}lora_rank = 0
image_conditioning = "$IMAGE_CONDITIONING"
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

# The decoder-only stage starts from the prior's backbone, so that its
# backbone (the prior's transformer, the encoder as trained, the decoder
# trained further) is a whole model folder.
cat >"$OUT/configs/vae-decoder.toml" <<EOF
[model]
backbone = "$OUT/prior/final/backbone"
lora_rank = 0
image_conditioning = "$IMAGE_CONDITIONING"
$(data_section)
[train]
stage = "vae"
vae_parts = "decoder"
out = "$OUT/vae-decoder"
batch_size = 4
max_steps = $DECODER_STEPS
lr = 2e-4
warmup_steps = 20
checkpoint_every = 100
color_augment = true
EOF

finetune_config() { # finetune_config OUT MASK_ACTION [BACKBONE]: BACKBONE defaults to the prior's
    local coding="" backbone=${3:-$OUT/prior/final/backbone}
    [[ $2 == true && $MASK_CODING != binary ]] && coding="mask_coding = \"$MASK_CODING\""
    finetune_toml "$backbone" "$coding" "$IMAGE_CONDITIONING" "$1" "$2"
}
finetune_config "$OUT/bridgev2w" true >"$OUT/configs/bridgev2w.toml"
# The planning model: the fine-tuned BridgeV2W continued on 3-frame clips
# (4 of every episode, batch 8, a lower learning rate, the flow loss on from
# the start), over the decoder stage's backbone (the one it is planned with).
{
    finetune_config "$OUT/bridgev2w-short" true "$OUT/vae-decoder/final/backbone" |
        sed -e "s|^lora_rank = 64$|init_weights = \"$OUT/bridgev2w/final/weights.safetensors\"\nlora_rank = 64|" \
            -e 's/^frames = 9$/frames = 3/' -e 's/^clips_per_video = 2$/clips_per_video = 4/' \
            -e 's/^batch_size = 4$/batch_size = 8/' -e "s/^max_steps = .*/max_steps = $SHORT_STEPS/" \
            -e 's/^lr = 5e-4$/lr = 2e-4/' -e 's/^warmup_steps = 100$/warmup_steps = 50/' \
            -e 's/^e_switch = 5$/e_switch = 0/' -e 's/^checkpoint_every = 250$/checkpoint_every = 200/'
} >"$OUT/configs/bridgev2w-short.toml"
finetune_config "$OUT/ablation-action-mlp" false >"$OUT/configs/ablation-action-mlp.toml"
# The evaluations' configs: the fine-tuning configs over the decoder stage's
# backbone (the same latents, the better decoder).
finetune_config "$OUT/bridgev2w" true "$OUT/vae-decoder/final/backbone" >"$OUT/configs/bridgev2w-eval.toml"
finetune_config "$OUT/ablation-action-mlp" false "$OUT/vae-decoder/final/backbone" \
    >"$OUT/configs/ablation-action-mlp-eval.toml"

SYNTH_ARGS=(--episodes-per-split "$EPISODES" --frames 17 --tasks "$TASKS")
ROBOT=franka
# Only a non-default engine joins the arguments (and so the fingerprint):
# the built-in world's runs keep theirs.
if [[ $ENGINE == mujoco ]]; then
    if [[ -z ${BRIDGEV2W_MUJOCO_PYTHON:-} ]]; then
        "$ROOT/scripts/setup-mujoco-venv.sh"
        export BRIDGEV2W_MUJOCO_PYTHON=$ROOT/.venv-mujoco/bin/python
    fi
    ROBOT=franka-robotiq
    SYNTH_ARGS+=(--engine mujoco --robot "$ROBOT")
fi
fresh synth "$(fingerprint "synth ${SYNTH_ARGS[*]}")"
if [[ -f $OUT/synth/meta/info.json && $MASK_CODING == links && ! -d $OUT/synth/labels ]]; then
    # Written before synth stored link labels: the same arguments give the
    # same episodes, now with labels/ (its fingerprint, and every stage
    # trained on it, stay valid).
    echo "== synth: no link labels (written by an older bridgev2w); writing it again"
    rm -rf "$OUT/synth"
fi
if [[ ! -f $OUT/synth/meta/info.json ]]; then
    rm -rf "$OUT/synth"
    stage synth "$BIN" synth --out "$OUT/synth" "${SYNTH_ARGS[@]}"
fi
train vae-image
train vae vae-image
train prior vae
train vae-decoder prior
evaluate() { # evaluate NAME JSON_NAME [SAMPLING...]: eval-run of OUT/NAME with the sampling flags into OUT/eval-JSON_NAME.json, kept when its run and settings are unchanged
    local name=$1 json=$2 fp
    shift 2
    local sampling=("$@")
    # "frames 1..": the scoring protocol (frame 0, the input, not scored
    # since 2026-11-25); "psnr per frame": the JSON's per-frame PSNR (the
    # figure's, since 2026-11-26); a change of protocol redoes the evaluations.
    fp=$(fingerprint "eval $name --max-videos $EVAL_VIDEOS --steps $EVAL_STEPS ${sampling[*]} frames 1.. psnr per frame" "$OUT/$name.inputs" "$OUT/vae-decoder.inputs")
    if [[ -f $OUT/eval-$json.json && $(cat "$OUT/eval-$json.inputs" 2>/dev/null) == "$fp" ]]; then
        echo "== eval $json: done before from the same run and settings, kept"
        return
    fi
    rm -f "$OUT/eval-$json.json" "$OUT/eval-$json.inputs"
    stage "eval $json" "$BIN" eval-run "$OUT/configs/$name-eval.toml" --run "$OUT/$name" \
        --max-videos "$EVAL_VIDEOS" --steps "$EVAL_STEPS" "${sampling[@]}" --json "$OUT/eval-$json.json"
    printf '%s\n' "$fp" >"$OUT/eval-$json.inputs"
}
# BridgeV2W is trained and scored before the ablation, so that a cut run
# has the main result first.
train bridgev2w prior
evaluate bridgev2w bridgev2w "${KEEP_ARGS[@]}"
[[ -n $KEEP_STATIC ]] && evaluate bridgev2w bridgev2w-generated
train ablation-action-mlp prior
evaluate ablation-action-mlp ablation-action-mlp "${KEEP_ARGS[@]}"
train bridgev2w-short bridgev2w vae-decoder

# The results' figures and videos go to the folder named after the results
# file (docs/results/ for docs/results.md): eval-report writes figures/,
# eval-grid grids/.
GRIDS="${RESULTS%.md}/grids"
SECTION=video
WORLD="the synthetic world"
if [[ $ENGINE == mujoco ]]; then
    GRIDS="${RESULTS%.md}/grids-mujoco"
    SECTION=video-mujoco
    WORLD="the MuJoCo world"
fi
GRID_CLIPS=4
grids() { # the side-by-side GIFs, kept when both runs and the settings are unchanged
    local fp split missing=0
    fp=$(fingerprint "grid --out $GRIDS --clips $GRID_CLIPS --steps $EVAL_STEPS ${KEEP_ARGS[*]}" "$OUT/bridgev2w.inputs" "$OUT/ablation-action-mlp.inputs" "$OUT/vae-decoder.inputs")
    for split in test unseen_camera unseen_scene; do
        [[ -f $GRIDS/$split.gif ]] || missing=1
    done
    if [[ $missing == 0 && $(cat "$OUT/grids.inputs" 2>/dev/null) == "$fp" ]]; then
        echo "== grids: done before from the same runs and settings, kept"
        return
    fi
    rm -f "$OUT/grids.inputs"
    stage grids "$BIN" eval-grid "$OUT/configs/bridgev2w-eval.toml" --run "$OUT/bridgev2w" \
        --compare "$OUT/configs/ablation-action-mlp-eval.toml" "$OUT/ablation-action-mlp" \
        --out "$GRIDS" --overwrite --clips "$GRID_CLIPS" --steps "$EVAL_STEPS" "${KEEP_ARGS[@]}"
    printf '%s\n' "$fp" >"$OUT/grids.inputs"
}
grids

PRE="$OUT/preamble.md"
{
    echo "Produced by \`scripts/reproduce-synthetic.sh\` on $(nproc) CPU core(s) ($(date -u +%Y-%m-%d))."
    echo "Dataset: \`bridgev2w synth --tasks $TASKS$([[ $ENGINE == mujoco ]] && echo ' --engine mujoco --robot franka-robotiq')\`, $([[ $ENGINE == mujoco ]] && echo 'Franka with a Robotiq gripper, simulated and rendered by MuJoCo' || echo Franka), 96x64, episodes of 17 frames ($EPISODES train/test/unseen_camera/unseen_scene); clips of 9 frames."
    echo "Models: \`random:$PRESET\` VAE ($([[ $PRESET == small2x* ]] && echo '4 latent channels, 2 blocks, 2x space, no time compression' || echo '16 latent channels, 3 blocks, 4x space, 4x time')) trained $VAE_IMAGE_STEPS steps on single frames (batch 16), then $VAE_STEPS steps on clips (batch 4$([[ $INFLATE == true ]] && echo ', starting from the image autoencoder applied frame by frame')) (L1 + KL, colours permuted and inverted at random);"
    echo "action-free I2V prior (4 layers, $([[ $PRESET == small2x-wide ]] && echo 8 || echo 4) heads x 32, patches of $([[ $PRESET == small2x* ]] && echo 4 || echo 2) latent pixels) trained $PRIOR_STEPS steps; then the VAE's decoder alone $DECODER_STEPS more steps on clips (encoder and latents unchanged; every model below is scored with it); BridgeV2W (ControlNet of 2 blocks + LoRA rank 64$([[ $MASK_CODING == links ]] && echo ', link-coded masks: `model.mask_coding = "links"`'))"
    echo "and the \`mask_action = false\` ablation (end-effector actions through an MLP, LoRA rank 64) fine-tuned $FT_STEPS steps each from the prior,"
    echo "batch 4, diffusion + dynamics (K = 4, 0.1) + flow (0.05 after 5 epochs; flow estimator: the differentiable Lucas-Kanade stand-in, no RAFT weights here)."
    echo "The planning model (stage \`bridgev2w-short\`, exported as \`bridgev2w-plan.safetensors\`): BridgeV2W continued $SHORT_STEPS steps on 3-frame clips (batch 8, flow loss from the start) for \`plan --weights\`; it is not scored here."
    echo "Each method is scored on the first clip of the first $EVAL_VIDEOS episodes of each split."
    if [[ -n $KEEP_STATIC ]]; then
        echo "Both methods' predictions keep the static scene (\`--keep-static $KEEP_STATIC\`, a sampler option beyond the paper): outside the region the robot's masks have swept in frames 0..t (dilated by $KEEP_STATIC px), frame t is the first frame; the row *every pixel generated* is BridgeV2W without it."
    fi
    echo
    echo "Wall time of the run that finished each stage: a stage resumed after a cut counts from its resume, and the machine's other work at the time is in it."
    echo
    echo "| stage | wall time (s) |"
    echo "|---|---|"
    awk -F'\t' '{printf "| %s | %s |\n", $1, $2}' "$LOG"
} >"$PRE"
"$BIN" eval-report --preamble "$PRE" --out "$RESULTS" \
    --entry "BridgeV2W (masks, ControlNet)=$OUT/eval-bridgev2w.json" \
    ${KEEP_STATIC:+--entry "BridgeV2W, every pixel generated=$OUT/eval-bridgev2w-generated.json"} \
    --entry "Ablation: actions through an MLP=$OUT/eval-ablation-action-mlp.json" \
    --training-run "vae-image=$OUT/vae-image" --training-run "vae=$OUT/vae" \
    --training-run "prior=$OUT/prior" --training-run "vae-decoder=$OUT/vae-decoder" \
    --training-run "bridgev2w=$OUT/bridgev2w" \
    --training-run "ablation-action-mlp=$OUT/ablation-action-mlp" \
    --grids "$GRIDS" --section "$SECTION" --title "Video prediction in $WORLD"

# The planning stages (PLAN_TRIALS > 0): the perfect model, then this run's
# model with its planning weights, each kept when its command and the runs
# it reads are unchanged. The settings are those of docs/results.md's
# `planning` and `planning-trained-plan` sections.
PLAN_TRIALS=${PLAN_TRIALS:-$([[ $ENGINE == mujoco ]] && echo 20 || echo 0)}
PLAN_EVAL_TRIALS=${PLAN_EVAL_TRIALS:-10}
planning() { # planning NAME INPUTS... -- PLAN-REPORT-ARGS...: plan-report into section NAME of RESULTS, kept when done before
    local name=$1 fp inputs=()
    shift
    while [[ $1 != -- ]]; do inputs+=("$1"); shift; done
    shift
    fp=$(fingerprint "plan-report $* --section $name --out $RESULTS" "$OUT/$DATA_STAGE.inputs" "${inputs[@]}")
    if [[ $(cat "$OUT/$name.inputs" 2>/dev/null) == "$fp" ]]; then
        echo "== $name: done before from the same runs and settings, kept"
        return
    fi
    rm -f "$OUT/$name.inputs"
    stage "$name" "$BIN" plan-report "$@" --section "$name" --out "$RESULTS"
    printf '%s\n' "$fp" >"$OUT/$name.inputs"
}
if ((PLAN_TRIALS > 0)); then
    planning "planning-$ENGINE" -- --engine "$ENGINE" --robot "$ROBOT" --models perfect --tasks reach,push,pick_place \
        --trials "$PLAN_TRIALS" --eval-trials "$PLAN_EVAL_TRIALS" --samples 64 --elites 8 --iters 3 --horizon 1 \
        --keep-elites --execute-best --max-steps 25 --translation-std-m 0.1 --waypoints 2
    # This run's model as a model folder (as assets/demo-model), float32.
    if [[ $(cat "$OUT/model.inputs" 2>/dev/null) != "$(cat "$OUT/bridgev2w-short.inputs")" ]]; then
        HALF_WEIGHTS=0 scripts/export-demo.sh "$OUT" "$OUT/model"
        cp "$OUT/bridgev2w-short.inputs" "$OUT/model.inputs"
    fi
    planning "planning-$ENGINE-trained" "$OUT/model.inputs" -- --engine "$ENGINE" --robot "$ROBOT" --models trained \
        --trained "$OUT/model" --plan-weights "$OUT/model/bridgev2w-plan.safetensors" --tasks reach,push,pick_place \
        --trials "$PLAN_TRIALS" --eval-trials "$PLAN_EVAL_TRIALS" --samples 16 --elites 4 --iters 3 --horizon 1 \
        --keep-elites --execute-best --max-steps 25 --translation-std-m 0.05 --waypoint-every-m 0.12 \
        --denoise-steps 1 --batch-noise shared --goal-latent pyramid --view-margin 0.2 --patience 8 \
        --plan-clip-frames 3 --decode-frames last
fi

if [[ ${EXPORT_DEMO:-0} == 1 ]]; then
    scripts/export-demo.sh "$OUT"
fi
echo "== done: $RESULTS"
