# Stage helpers shared by the reproduction scripts (sourced, not run):
# timed stages, input fingerprints, and resumable training stages.
# The sourcing script sets ROOT (the repository), OUT (its output folder)
# and DATA_STAGE (the stage whose OUT/DATA_STAGE.inputs every training stage
# depends on), then calls setup_run, which sets BIN (the bridgev2w binary)
# and LOG (the timings file).

setup_run() { # BIN: $BRIDGEV2W, or target/release/bridgev2w built now; OUT/configs and LOG made
    BIN=${BRIDGEV2W:-$ROOT/target/release/bridgev2w}
    if [[ -z ${BRIDGEV2W:-} ]]; then
        echo "== building bridgev2w (release)"
        "$ROOT/scripts/setup-venv.sh"
        cargo build --release -p bridgev2w-cli
    fi
    [[ -x $BIN ]] || { echo "error: $BIN is not an executable (set BRIDGEV2W)" >&2; exit 1; }
    mkdir -p "$OUT/configs"
    LOG="$OUT/timings.tsv"
    touch "$LOG"
}

stage() { # stage NAME COMMAND...: runs it, records its wall time (replacing an earlier record)
    local name=$1 t0
    shift
    echo "== $name: $*"
    t0=$(date +%s)
    "$@"
    awk -F'\t' -v n="$name" '$1 != n' "$LOG" >"$LOG.tmp"
    printf '%s\t%s\n' "$name" "$(($(date +%s) - t0))" >>"$LOG.tmp"
    mv "$LOG.tmp" "$LOG"
}

fingerprint() { # fingerprint TEXT FILE...: 16 hex digits of TEXT and the files
    { printf '%s\n' "$1"; shift; cat "$@"; } | sha256sum | cut -c1-16
}

fresh() { # fresh NAME FP: moves OUT/NAME aside when it was made from other inputs
    local name=$1 fp=$2 old
    old=$(cat "$OUT/$name.inputs" 2>/dev/null || true)
    if [[ -e $OUT/$name && $old != "$fp" ]]; then
        echo "== $name: its inputs changed (${old:-unrecorded} -> $fp); moving it to $OUT/$name.stale-${old:-unrecorded} and redoing it"
        rm -rf "$OUT/$name.stale-${old:-unrecorded}"
        mv "$OUT/$name" "$OUT/$name.stale-${old:-unrecorded}"
    fi
    printf '%s\n' "$fp" >"$OUT/$name.inputs"
}

train() { # train NAME UPSTREAM...: trains OUT/configs/NAME.toml unless OUT/NAME/final exists; resumes a cut run
    local name=$1 resume=() ups=() u fp base steps old_fp old_steps
    shift
    for u in "$DATA_STAGE" "$@"; do ups+=("$OUT/$u.inputs"); done
    fp=$(fingerprint "train $name" "$OUT/configs/$name.toml" "${ups[@]}")
    # The same inputs but for the step budget (OUT/NAME.base), grown: the
    # learning rate is constant after warm-up and a resumed run is
    # bit-identical to an uninterrupted one, so the longer run continues from
    # the stage's checkpoints instead of starting over.
    base=$(fingerprint "train $name" <(grep -v '^max_steps = ' "$OUT/configs/$name.toml") "${ups[@]}")
    steps=$(sed -n 's/^max_steps = //p' "$OUT/configs/$name.toml")
    old_fp=$(cat "$OUT/$name.inputs" 2>/dev/null || true)
    old_steps=$(cat "$OUT/$name.steps" 2>/dev/null || true)
    if [[ -d $OUT/$name/checkpoints && -n $old_fp && $old_fp != "$fp" && -n $old_steps
        && $(cat "$OUT/$name.base" 2>/dev/null) == "$base" && $steps -ge $old_steps ]]; then
        echo "== $name: only its step budget changed ($old_steps -> $steps): continuing from its checkpoints"
        rm -rf "$OUT/$name/final"
        printf '%s\n' "$fp" >"$OUT/$name.inputs"
    else
        fresh "$name" "$fp"
    fi
    printf '%s\n' "$base" >"$OUT/$name.base"
    printf '%s\n' "$steps" >"$OUT/$name.steps"
    if [[ -f $OUT/$name/final/weights.safetensors ]]; then
        echo "== $name: done before from the same inputs, kept"
        return
    fi
    if [[ -d $OUT/$name/checkpoints ]]; then
        resume=(--resume "$OUT/$name")
    elif [[ -e $OUT/$name ]]; then
        resume=(--overwrite) # cut before its first checkpoint: nothing to keep
    fi
    stage "$name" "$BIN" train "$OUT/configs/$name.toml" --quiet "${resume[@]}"
}

finetune_toml() { # BACKBONE CODING_LINE IMAGE_CONDITIONING OUT MASK_ACTION: a fine-tuning run's config (the script's data_section and FT_STEPS)
    local coding=""
    [[ -n $2 ]] && coding="$2"$'\n'
    cat <<EOF
[model]
backbone = "$1"
${coding}lora_rank = 64
lora_alpha = 64
controlnet_layers = 2
action_hidden = 128
image_conditioning = "$3"
$(data_section)
[train]
out = "$4"
batch_size = 4
max_steps = $FT_STEPS
lr = 5e-4
warmup_steps = 100
e_switch = 5
checkpoint_every = 250
[ablation]
mask_action = $5
EOF
}
