#!/usr/bin/env bash
# Exports the fine-tuned BridgeV2W of a `scripts/reproduce-synthetic.sh` run
# as the shipped demo model, assets/demo-model (the default model of
# `bridgev2w demo`): the backbone folder of the decoder stage (the prior's
# transformer with the decoder trained further), the fine-tuned weights and
# the fine-tuning config with paths relative to the repository root; and,
# when the run has it, the planning model (stage bridgev2w-short, weights
# continued on 3-frame clips: `plan --weights
# assets/demo-model/bridgev2w-plan.safetensors --clip-frames 3`) with its
# config, plan-config.toml.
# Called by reproduce-synthetic.sh with EXPORT_DEMO=1. The weights are
# stored in float16 (half the size in git; the loaders cast to the model's
# dtype), their safetensors metadata (the mask coding) kept; HALF_WEIGHTS=0
# keeps them as trained (float32).
#
# Usage: scripts/export-demo.sh [OUT_DIR [DEST]]
#   (defaults: runs/reproduce, assets/demo-model; reproduce-synthetic.sh's
#   planning stages export a run's model to OUT_DIR/model)
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
OUT=${1:-runs/reproduce}
DEST=${2:-assets/demo-model}
for f in "$OUT/vae-decoder/final/backbone" "$OUT/bridgev2w/final/weights.safetensors" "$OUT/configs/bridgev2w-eval.toml"; do
    [[ -e $f ]] || { echo "error: $f is missing: run scripts/reproduce-synthetic.sh $OUT first" >&2; exit 1; }
done
rm -rf "$DEST.tmp"
mkdir -p "$DEST.tmp"
cp -r "$OUT/vae-decoder/final/backbone" "$DEST.tmp"/backbone
cp "$OUT/bridgev2w/final/weights.safetensors" "$DEST.tmp"/bridgev2w.safetensors
# The configs as they stand, paths relative to the repository root: the
# backbone is the exported one, the dataset and run folders the
# reproduction's (rerun the script to recreate them).
repo_config() { # repo_config CONFIG: CONFIG with the repository's paths
    sed -e "s|\"$OUT/vae-decoder/final/backbone\"|\"$DEST/backbone\"|" \
        -e "s|\"$ROOT/|\"|" "$1"
}
{
    echo "# BridgeV2W fine-tuning config of this model (scripts/reproduce-synthetic.sh $OUT);"
    echo "# paths are relative to the repository root. The fine-tuning itself ran over the"
    echo "# prior's backbone, which differs from this one only in the decoder (the stage"
    echo "# vae-decoder trained it further; the encoder, the latents and the transformer are the same)."
    repo_config "$OUT/configs/bridgev2w-eval.toml"
} >"$DEST.tmp"/train-config.toml
if [[ -f $OUT/bridgev2w-short/final/weights.safetensors ]]; then
    cp "$OUT/bridgev2w-short/final/weights.safetensors" "$DEST.tmp"/bridgev2w-plan.safetensors
    {
        echo "# The planning model's config (scripts/reproduce-synthetic.sh $OUT, stage bridgev2w-short):"
        echo "# the fine-tuned BridgeV2W (train-config.toml) continued on 3-frame clips; paths"
        echo "# relative to the repository root, the run folders the reproduction's."
        repo_config "$OUT/configs/bridgev2w-short.toml"
    } >"$DEST.tmp"/plan-config.toml
fi
PY=${PYTHON:-.venv/bin/python}
if [[ ${HALF_WEIGHTS:-1} != 0 ]]; then
[[ -x $PY ]] || { echo "error: $PY not found: run scripts/setup-venv.sh first" >&2; exit 1; }
"$PY" - "$DEST.tmp" <<'PYTHON'
import pathlib, sys
import torch
from safetensors import safe_open
from safetensors.torch import save_file
for path in sorted(pathlib.Path(sys.argv[1]).rglob("*.safetensors")):
    with safe_open(str(path), "pt") as f:
        meta = f.metadata()
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    half = {k: t.half() if t.dtype == torch.float32 else t for k, t in tensors.items()}
    save_file(half, str(path), metadata=meta)
PYTHON
fi
rm -rf "$DEST" && mv "$DEST.tmp" "$DEST"
du -sh "$DEST"
